"""DAQ adapter throughput: per-sample driver messages -> contract SensorBlocks.

The sample pass (bags/paper_pass) as the DAQ simulator publishes it: 19 channels at 2 kHz and
position/speed at 200 Hz = 38.4 k samples/s in 18 200 messages/s on 10 driver topics
(Float64MultiArray with the 11 guideway channels, 4 Imu, 4 Range, Odometry). The test line needs
34 k samples/s (17 channels at 2 kHz). Prints, measured in this run:
  - the batching core alone (no ROS) on stand-in messages, against a peer: the bare loop that only
    reads the same fields from the same messages (the floor of any per-message Python code);
  - the daq_sim -> daq_adapter chain over DDS on loopback: at 1x to 3x real time with the drivers'
    sensor-data QoS (best effort: what is lost shows as samples not received; "took" longer than
    the stream's length / rate means the simulator itself could not keep the pace), and unpaced
    with reliable QoS (nothing lost: DDS flow control paces the simulator), each with samples/s, the ratio to 34 k samples/s, the
    adapter's and simulator's CPU use (cores) and the samples missing (where it drops them).

    .venv/bin/python bench/bench_daq_adapter.py [--seconds 8] [--domain 97]
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

from maglev_ros.daq_stream.batcher import BlockBatcher  # noqa: E402
from maglev_ros.daq_stream.mapping import load_mapping, load_metadata_file  # noqa: E402
from maglev_ros.daq_stream.sim import plain_message, source_from_bag, write_config  # noqa: E402

BAG = ROOT / "bags" / "paper_pass"
NEED = 34_000.0          # 17 channels x 2 kHz


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (/proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def bench_core(src, mapping_path, meta_path):
    mapping = load_mapping(mapping_path, load_metadata_file(meta_path))
    idx, rows = src.order()
    msgs = [(src.streams[i].topic, plain_message(src.streams[i].msg_type, src.streams[i].stamps_ns[r],
                                                 src.streams[i].values[r])) for i, r in zip(idx, rows)]
    getters = {d.topic: [c.getter() for c in d.channels] for d in mapping.drivers.values()}
    best_peer = best_core = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for topic, m in msgs:
            [g(m) for g in getters[topic]]
        best_peer = min(best_peer, time.perf_counter() - t)
        b = BlockBatcher(mapping)
        t = time.perf_counter()
        for topic, m in msgs:
            b.add_message(topic, m)
        b.flush()
        best_core = min(best_core, time.perf_counter() - t)
    assert b.stats().total("samples") == src.samples and b.stats().total("missing") == 0
    n = src.samples
    print(f"core (no ROS): {len(msgs)} messages, {n} samples")
    print(f"  peer: read the mapped fields only   {n / best_peer:12,.0f} samples/s")
    print(f"  BlockBatcher.add_message            {n / best_core:12,.0f} samples/s  = {n / best_core / NEED:6.1f}x "
          f"the line's 34 k/s; {best_peer / best_core:.2f}x the peer's rate")
    try:       # what the node does: serialised messages, fields read at their CDR offsets
        from rclpy.serialization import deserialize_message

        from maglev_ros.nodes.daq_adapter import DRIVER_CLASSES
        from maglev_ros.nodes.daq_sim import _Serialised, _template
    except ImportError:
        return
    ser = [_Serialised(_template(DRIVER_CLASSES[s.msg_type], s.msg_type, s.topic), s.msg_type, s.values.shape[1])
           for s in src.streams]
    raw = [(src.streams[i].topic, ser[i].message(int(src.streams[i].stamps_ns[r]), src.streams[i].values[r]))
           for i, r in zip(idx, rows)]
    classes = {s.topic: DRIVER_CLASSES[s.msg_type] for s in src.streams}
    best_cdr = best_rclpy = float("inf")
    for _ in range(2):
        b = BlockBatcher(mapping)
        t = time.perf_counter()
        for topic, buf in raw:
            b.add_cdr(topic, buf)
        b.flush()
        best_cdr = min(best_cdr, time.perf_counter() - t)
        assert b.stats().total("samples") == n
        b = BlockBatcher(mapping)
        t = time.perf_counter()
        for topic, buf in raw:
            b.add_message(topic, deserialize_message(buf, classes[topic]))
        b.flush()
        best_rclpy = min(best_rclpy, time.perf_counter() - t)
    print(f"  BlockBatcher.add_cdr (the node's)   {n / best_cdr:12,.0f} samples/s  = {n / best_cdr / NEED:6.1f}x; "
          f"rclpy deserialisation + add_message {n / best_rclpy:,.0f} samples/s ({best_rclpy / best_cdr:.1f}x slower)")


def bench_ros(env, meta_path, mapping_path, seconds, rate, reliable):
    """One run; unpaced (reliable: nothing lost) the adapter waits for a lagging topic as long as it takes."""
    import rclpy
    from rclpy.context import Context
    from rclpy.experimental import EventsExecutor
    from std_msgs.msg import String

    from maglev_ros.nodes._lifecycle import QOS_STATUS_READER, TOPIC_STATUS, NodeStatus
    py = [sys.executable, "-m"]
    adapter = subprocess.Popen(py + ["maglev_ros.nodes.daq_adapter", "--ros-args", "-p", f"mapping:={mapping_path}",
                                     "-p", f"metadata:={meta_path}", "-p", f"idle_flush_s:={0.0 if not rate else 0.5}",
                                     "-p", f"max_wait_s:={60.0 if not rate else 0.5}"],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("bench_daq", context=ctx)
    last = {}

    def on_status(m):
        st = NodeStatus.from_json(m.data)
        if st is not None and st.node == "daq_adapter" and st.detail:
            last["counts"] = json.loads(st.detail)
    node.create_subscription(String, TOPIC_STATUS, on_status, QOS_STATUS_READER)
    ex = EventsExecutor(context=ctx)
    ex.add_node(node)
    try:
        end = time.monotonic() + 60
        while "counts" not in last and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.1)
        a0 = cpu_s(adapter.pid)
        sim = subprocess.Popen(py + ["maglev_ros.nodes.daq_sim", "--ros-args", "-p", f"bag:={BAG}",
                                     "-p", f"duration_s:={seconds}", "-p", f"rate:={rate}",
                                     "-p", f"reliable:={'true' if reliable else 'false'}", "-p", "wait_subscribers:=1"],
                               env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        # the sim's clock starts when the adapter has subscribed: from its first message to its exit
        s_cpu = 0.0
        while sim.poll() is None:
            ex.spin_once(timeout_sec=0.05)
            try:
                s_cpu = cpu_s(sim.pid)
            except (FileNotFoundError, ProcessLookupError):
                pass
        log = sim.stdout.read()
        if "published" not in log:
            print(f"  the simulator failed (exit {sim.returncode}):\n{log[-2000:]}")
        took = float(log.rsplit(" in ", 1)[1].split(" s")[0]) if "published" in log else float("nan")
        a_cpu = cpu_s(adapter.pid) - a0
        target = sum(len(r[0]) * len(r[2]) for r in source_from_bag(BAG, 0.0, seconds).truth.values())
        end = time.monotonic() + 10
        while time.monotonic() < end and last["counts"].get("samples", 0) + last["counts"].get("missing", 0) < target:
            ex.spin_once(timeout_sec=0.1)
        end = time.monotonic() + 2.5          # the last status after the idle flush
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.1)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        adapter.send_signal(2)
        adapter.wait(timeout=20)
    c = last["counts"]
    got = c["samples"]
    label = f"{'unpaced' if not rate else f'{rate:g}x real time'}, {'reliable' if reliable else 'best effort'}"
    print(f"  {label:28s} {got / took:10,.0f} samples/s = {got / took / NEED:5.2f}x 34 k/s; adapter "
          f"{a_cpu / took:4.2f} cores, simulator {s_cpu / took:4.2f} cores; {target} sent, {got} in blocks, "
          f"missing {c['missing']} ({100.0 * (target - got) / target:.2f} % not received), late {c['late']}, "
          f"gaps {c['gaps']}; {took:.2f} s")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=8.0, help="stream length (the bag has 12.6 s)")
    ap.add_argument("--domain", type=int, default=97)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_daq_"))
    src = source_from_bag(BAG, 0.0, args.seconds)
    meta, mapping = write_config(src, tmp)
    bench_core(src, mapping, meta)
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    print(f"daq_sim -> daq_adapter over DDS ({args.seconds:g} s of the pass, {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.1f}):")
    for rate, reliable in ((1.0, False), (1.5, False), (2.0, False), (3.0, False), (0.0, True)):
        bench_ros(env, meta, mapping, args.seconds, rate, reliable)


if __name__ == "__main__":
    main()
