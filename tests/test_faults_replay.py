"""Replay under back-pressure: a subscriber that cannot keep up slows a ``--fast`` replay down
(never a crash, never a lost block), a best-effort one never holds it, a gone one ends it in
bounded time with one line naming the topic, and Ctrl-C while it waits ends it cleanly.

The ROS tests run a real graph: the replay process and subscriber processes started from this
file (``python tests/test_faults_replay.py OUT TOPIC QOS SLEEP_S``), over a 30-min recording of
one topic (position, 100 Hz, 0.1 s blocks: 18000 messages, more than a DDS writer's and a
reader's history together hold, so a slow subscriber fills them).
"""
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from maglev_ros.errors import UserError
from maglev_ros.replay_timing import Backpressure, Stalled
from rosgraph import domain_id

HERE = Path(__file__).resolve().parent
TOPIC = "/testline/vehicle/position"
RATE_HZ = 100.0
BLOCK_SAMPLES = 10
DURATION_S = 1800.0


class FakeTime:
    def __init__(self, t=100.0):
        self.t = t

    def __call__(self):
        return self.t


# ------------------------------------------------------------------------- no ROS: the policy
def test_refused_message_is_offered_again_after_doubling_waits_up_to_the_cap():
    now = FakeTime()
    bp = Backpressure(stall_timeout_s=60.0, first_wait_s=0.01, max_wait_s=0.05, now=now)
    assert [bp.refused(TOPIC) for _ in range(5)] == pytest.approx([0.01, 0.02, 0.04, 0.05, 0.05])
    now.t += 2.0
    bp.accepted(TOPIC, offer_s=2.0)
    # the next refusal is a new stall: from the first wait again, and the refused message counted
    assert bp.refused(TOPIC) == pytest.approx(0.01)
    bp.accepted(TOPIC, offer_s=0.5)
    bp.accepted(TOPIC, offer_s=1e-5)                 # queued at once: not held back
    assert bp.refused_n == {TOPIC: 2}
    assert bp.held_n == {TOPIC: 2} and bp.held_s[TOPIC] == pytest.approx(2.5)
    assert bp.accepted_n == {TOPIC: 3}


def test_stall_past_the_bound_raises_naming_the_topic():
    now = FakeTime()
    bp = Backpressure(stall_timeout_s=10.0, warn_after_s=5.0, now=now)
    bp.refused(TOPIC)
    now.t += 4.0
    bp.refused(TOPIC)
    assert not bp.warn_due()
    now.t += 2.0
    assert bp.warn_due() and not bp.warn_due()      # one warning per stall
    now.t += 4.5
    with pytest.raises(Stalled, match=f"^{TOPIC}: a reliable subscriber took no message for 10 s") as err:
        bp.refused(TOPIC)
    assert "\n" not in str(err.value) and err.value.topic == TOPIC


def test_a_message_taken_ends_the_stall_so_slow_progress_never_times_out():
    now = FakeTime()
    bp = Backpressure(stall_timeout_s=10.0, now=now)
    for _ in range(5):                               # 40 s of refusals, each stall 8 s long
        bp.refused(TOPIC)
        now.t += 8.0
        bp.refused(TOPIC)
        bp.accepted(TOPIC, offer_s=8.0)
    assert bp.stalled_s() == 0.0 and bp.refused_n == {TOPIC: 5}


def test_drain_budget_covers_a_full_history_at_the_pace_the_subscriber_showed():
    now = FakeTime(0.0)
    bp = Backpressure(stall_timeout_s=30.0, history_limit=1000, now=now)
    for _ in range(200):
        bp.accepted(TOPIC, offer_s=1e-5)
    assert bp.drain_budget_s(TOPIC) == 30.0          # never held back: the stall allowance only
    now.t = 1.0
    bp.accepted(TOPIC, offer_s=1.0)                  # first held at t = 0
    now.t = 40.0
    for _ in range(79):                              # 80 taken in 40 s: 2 per second
        bp.accepted(TOPIC, offer_s=0.5)
    # a full history of 1000 at 2 per second needs 500 s
    assert bp.drain_budget_s(TOPIC) == pytest.approx(30.0 + 1000 / 2.0)
    for _ in range(1920):                            # 2000 taken by t = 40 s: 50 per second,
        bp.accepted(TOPIC, offer_s=0.01)             # a history in 20 s, but paced for 40 s
    assert bp.drain_budget_s(TOPIC) == pytest.approx(30.0 + 40.0)


def test_pace_is_credited_to_subscribers_only_beyond_a_busy_machines_delays():
    bp = Backpressure()
    for _ in range(4):                               # four publish calls delayed 10 ms: no pacing
        bp.accepted("/a", offer_s=0.01)
    bp.accepted("/b", offer_s=3.0)
    bp.refused("/c")
    bp.accepted("/c", offer_s=0.2)                   # refused once: its writer was full
    assert bp.paced(wall_s=20.0) == ["/b", "/c"]
    assert bp.paced(wall_s=100.0) == ["/c"]          # 3 s of 100 s: below 5 %


def test_non_positive_stall_timeout_is_a_user_error():
    with pytest.raises(UserError, match="stall_timeout_s"):
        Backpressure(stall_timeout_s=0.0)


# ------------------------------------------------------------------------- ROS: a real graph
@pytest.fixture(scope="module")
def long_bag(tmp_path_factory):
    from bagfactory import VEHICLE_POSITION, make_metadata, write_contract_bag
    n = int(DURATION_S * RATE_HZ)
    t = np.arange(n) / RATE_HZ
    topics = {VEHICLE_POSITION: (("position_m", "speed_mps"), ("m", "m/s"), RATE_HZ,
                                 np.stack([6.944 * t, np.full(n, 6.944)], axis=1))}
    return write_contract_bag(tmp_path_factory.mktemp("long") / "pass30min",
                              make_metadata(topics), topics, block_s=BLOCK_SAMPLES / RATE_HZ)


def _expected_stamps_ns() -> list[int]:
    from bagfactory import block_stamp_ns
    n_blocks = int(DURATION_S * RATE_HZ) // BLOCK_SAMPLES
    return [block_stamp_ns(0, k * BLOCK_SAMPLES, RATE_HZ) for k in range(n_blocks)]


@pytest.fixture()
def env():
    # a domain of its own (other ROS tests use 20 and up), DDS on loopback, this tree first
    return dict(os.environ, ROS_DOMAIN_ID=str(domain_id(1)),
                ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))


class _Procs:
    def __init__(self):
        self.procs = []

    def start(self, args, env, **kw):
        p = subprocess.Popen([sys.executable, *args], env=env, **kw)
        self.procs.append(p)
        return p

    def stop(self):
        for p in self.procs:
            if p.poll() is None:
                p.kill()
                p.wait()


@pytest.fixture()
def procs():
    ps = _Procs()
    yield ps
    ps.stop()


def _subscriber(procs, env, out: Path, qos: str, sleep_s: float):
    return procs.start([str(Path(__file__)), str(out), TOPIC, qos, str(sleep_s)], env)


def _replay(procs, env, bag, n_subscribers: int, stall_timeout_s: float):
    return procs.start(["-m", "maglev_ros.cli", "replay", str(bag), "--fast", "--quiet",
                        "--wait-subscribers", str(n_subscribers),
                        "--ros-args", "-p", f"stall_timeout_s:={stall_timeout_s}"],
                       env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.ros
def test_fast_replay_waits_for_a_slow_reliable_subscriber_and_ignores_a_stuck_best_effort_one(
        long_bag, env, procs, tmp_path):
    slow = tmp_path / "slow.json"
    _subscriber(procs, env, slow, "reliable", 0.0005)
    # best effort and stuck on its first message for good: it must not hold the replay back
    _subscriber(procs, env, tmp_path / "stuck.json", "best_effort", 3600.0)
    # a stall of 20 s ends the replay with an error: more than a slow subscriber's legitimate
    # stalls (until its next acknowledgement), so only a writer held by the stuck one would hit it
    rep = _replay(procs, env, long_bag, n_subscribers=2, stall_timeout_s=20.0)
    out, err = rep.communicate(timeout=240)
    assert rep.returncode == 0, err
    assert "Traceback" not in err
    # the publish path waited for room in the writer's history: the subscriber sleeps 18000 x
    # 0.5 ms = 9 s, the writer's and reader's histories hold 5000 each, so the replay must have
    # waited 4 s at least; without a reliable subscriber, scheduling delays inside the publish
    # calls added up to 0.1 s at most on a loaded 2-core machine
    summary = next(line for line in err.splitlines() if "published 18000 messages" in line)
    held = re.search(rf"a reliable subscriber of {TOPIC} set the pace: \d+ message\(s\) "
                     r"waited ([\d.]+) s for room", summary)
    assert held is not None and float(held.group(1)) > 2.0, summary
    procs.procs[0].wait(timeout=120)
    got = json.loads(slow.read_text())
    assert got["stamps_ns"] == _expected_stamps_ns()   # every block once, in order
    assert set(got["n_samples"]) == {BLOCK_SAMPLES * 2}


@pytest.mark.ros
@pytest.mark.slow     # the stall bound itself: test_stall_past_the_bound_raises_naming_the_topic (no DDS)
def test_killed_subscriber_ends_the_replay_in_bounded_time_with_one_line_naming_the_topic(
        long_bag, env, procs, tmp_path):
    out = tmp_path / "victim.json"
    victim = _subscriber(procs, env, out, "reliable", 3600.0)
    rep = _replay(procs, env, long_bag, n_subscribers=1, stall_timeout_s=4.0)
    first = out.with_suffix(".first")
    while not first.exists():          # it took its first message: kill it mid-replay
        assert rep.poll() is None and victim.poll() is None
        time.sleep(0.05)
    victim.send_signal(signal.SIGKILL)
    _, err = rep.communicate(timeout=120)
    assert rep.returncode == 1, err
    assert "Traceback" not in err
    assert f"{TOPIC}: a reliable subscriber has taken nothing" in err   # the warning first
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"replay: error: {TOPIC}: ") and "stopped" in last, last


@pytest.mark.ros
def test_ctrl_c_while_waiting_for_a_subscriber_ends_the_replay_cleanly(long_bag, env, procs, tmp_path):
    _subscriber(procs, env, tmp_path / "stuck.json", "reliable", 3600.0)
    rep = _replay(procs, env, long_bag, n_subscribers=1, stall_timeout_s=300.0)
    seen = []
    for line in rep.stderr:                        # until the replay says it is waiting
        seen.append(line)
        if f"{TOPIC}: a reliable subscriber has taken nothing" in line:
            break
    assert rep.poll() is None, "".join(seen)
    rep.send_signal(signal.SIGINT)
    _, err = rep.communicate(timeout=60)
    assert rep.returncode == 130, err
    assert "Traceback" not in "".join(seen) + err


# ------------------------------------------------------------------------- subscriber process
def _subscribe(out: str, topic: str, qos: str, sleep_s: float, idle_s: float = 2.0) -> None:
    """Record each message's stamp and sample count, sleeping ``sleep_s`` per message; write OUT
    ``idle_s`` after the last one (OUT with suffix .first marks the first)."""
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data

    from maglev_msgs.msg import SensorBlock
    from maglev_ros.nodes._common import QOS_STREAM

    rclpy.init()
    node = Node("slow_subscriber")
    rec = {"stamps_ns": [], "n_samples": []}
    last = {"t": None}

    def on_block(msg):
        if last["t"] is None:
            Path(out).with_suffix(".first").touch()
        rec["stamps_ns"].append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        rec["n_samples"].append(len(msg.data))
        time.sleep(sleep_s)
        last["t"] = time.monotonic()

    node.create_subscription(SensorBlock, topic, on_block,
                             QOS_STREAM if qos == "reliable" else qos_profile_sensor_data)
    ex = EventsExecutor()
    ex.add_node(node)
    while last["t"] is None or time.monotonic() - last["t"] < idle_s:
        ex.spin_once(timeout_sec=0.1)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    Path(out).write_text(json.dumps(rec))


if __name__ == "__main__":
    _subscribe(sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]))
