"""Replay throughput: 17 channels at 2 kHz in 0.1 s blocks.

Prints, measured in one run on the same bag:
  - plain rosbags: raw message iteration and full deserialisation (the peer),
  - our BagReader.iter_raw (what replay reads) and iter_blocks (what analysis reads),
  - the replay node publishing as fast as possible over DDS into a subscriber process,
as blocks/s, samples/s, the ratio to the bag's real-time rate (target >= 100x) and the ratio
of our reading to rosbags alone (target >= 0.8x).

    .venv/bin/python bench/bench_replay.py [--minutes 5]
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from maglev_ros.bag_reader import BagReader  # noqa: E402
from maglev_ros.bag_writer import BagWriter  # noqa: E402
from maglev_ros.sensor_block import Block, typestore  # noqa: E402

N_CH, FS, BLOCK_N = 17, 2000.0, 200
TOPIC = "/testline/guideway/accel"


def write_bag(path: Path, minutes: float) -> int:
    n_blocks = int(minutes * 60 * FS / BLOCK_N)
    chans = tuple(f"G{i}" for i in range(N_CH))
    meta = {"schema": "maglev-testline/1",
            "line": {"spans": [{"id": "S1", "start_m": 0.0, "length_m": 24.768}]},
            "sensors": {c: {"topic": TOPIC, "quantity": "acceleration", "direction": "vertical",
                            "span": "S1", "position_m": float(i), "side": "left"}
                        for i, c in enumerate(chans)},
            "run": {"kind": "ambient"}}
    rng = np.random.default_rng(0)
    data = rng.standard_normal((BLOCK_N, N_CH)).astype(np.float32)
    with BagWriter(path, meta) as w:
        for k in range(n_blocks):
            w.write_block(TOPIC, Block(1_700_000_000_000_000_000 + int(k * BLOCK_N / FS * 1e9),
                                       "guideway", FS, chans, ("m/s^2",) * N_CH, data))
    return n_blocks


def timed(fn, repeat=3):
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        n = fn()
        best = min(best, time.perf_counter() - t)
    return n, best


def rosbags_raw(path):
    from rosbags.highlevel import AnyReader
    with AnyReader([Path(path)], default_typestore=typestore()) as r:
        return sum(1 for _ in r.messages(connections=[c for c in r.connections if c.topic == TOPIC]))


def rosbags_deser(path):
    from rosbags.highlevel import AnyReader
    n = 0
    with AnyReader([Path(path)], default_typestore=typestore()) as r:
        for conn, _, raw in r.messages(connections=[c for c in r.connections if c.topic == TOPIC]):
            msg = r.deserialize(raw, conn.msgtype)
            n += msg.data.size > 0
    return n


def ours_raw(path):
    with BagReader(path) as r:
        return sum(1 for _ in r.iter_raw(topics=[TOPIC]))


def iteration_only(path):
    """(rosbags, ours) seconds for the message loop alone, both readers already open."""
    from rosbags.highlevel import AnyReader
    with AnyReader([Path(path)], default_typestore=typestore()) as r:
        conns = [c for c in r.connections if c.topic == TOPIC]
        t = time.perf_counter()
        n1 = sum(1 for _ in r.messages(connections=conns))
        t_rb = time.perf_counter() - t
    with BagReader(path) as r:
        t = time.perf_counter()
        n2 = sum(1 for _ in r.iter_raw(topics=[TOPIC]))
        t_ours = time.perf_counter() - t
    assert n1 == n2
    return t_rb, t_ours


def ours_blocks(path):
    with BagReader(path) as r:
        return sum(1 for _ in r.iter_blocks(topics=[TOPIC]))


def replay_over_dds(path, n_blocks, tmp):
    env = dict(os.environ, ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = Path(tmp) / "probe.json"
    probe = subprocess.Popen([sys.executable, str(HERE.parent / "tests" / "ros_probe.py"),
                              str(out), "600", TOPIC], env=env)
    t = time.perf_counter()
    rep = subprocess.run([sys.executable, "-m", "maglev_ros.cli", "replay", str(path), "--fast",
                          "--quiet", "--wait-subscribers", "1", "--no-clock"],
                         env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    probe.wait(timeout=120)
    import json
    got = len(json.loads(out.read_text())["blocks"][TOPIC])
    if rep.returncode != 0:
        print(rep.stderr)
    import re
    m = re.search(r"in ([0-9.]+) s wall", rep.stderr)
    loop_wall = float(m.group(1)) if m else float("nan")
    return got, wall, loop_wall


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=5.0)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "bench"
        n_blocks = write_bag(bag, a.minutes)
        dur_s = n_blocks * BLOCK_N / FS
        samples = n_blocks * BLOCK_N * N_CH
        print(f"bag: {n_blocks} blocks, {dur_s:.0f} s of {N_CH} channels at {FS:g} Hz "
              f"({sum(f.stat().st_size for f in bag.iterdir()) / 1e6:.1f} MB)")
        rows = []
        for name, fn in [("rosbags raw iteration", rosbags_raw),
                         ("rosbags deserialise", rosbags_deser),
                         ("BagReader.iter_raw", ours_raw),
                         ("BagReader.iter_blocks", ours_blocks)]:
            n, t = timed(lambda fn=fn: fn(bag))
            assert n == n_blocks, (name, n)
            rows.append((name, t))
        base = dict(rows)
        it = [iteration_only(bag) for _ in range(3)]
        t_rb, t_ours = min(x[0] for x in it), min(x[1] for x in it)
        got, wall, loop_wall = replay_over_dds(bag, n_blocks, tmp)
        print(f"{'reader':28s} {'wall s':>8s} {'blocks/s':>10s} {'Msamples/s':>11s} {'x realtime':>11s} {'vs rosbags':>11s}")
        for name, t in rows:
            peer = base["rosbags raw iteration"] if "raw" in name else base["rosbags deserialise"]
            print(f"{name:28s} {t:8.3f} {n_blocks / t:10.0f} {samples / t / 1e6:11.1f} "
                  f"{dur_s / t:11.0f} {peer / t:10.2f}x")
        print(f"{'raw loop only, readers open':28s} {t_ours:8.3f} {n_blocks / t_ours:10.0f} "
              f"{samples / t_ours / 1e6:11.1f} {dur_s / t_ours:11.0f} {t_rb / t_ours:10.2f}x  "
              "(rows above include opening the bag: BagReader reads metadata and topic infos)")
        print(f"{'replay --fast over DDS':28s} {wall:8.3f} {n_blocks / wall:10.0f} "
              f"{samples / wall / 1e6:11.1f} {dur_s / wall:11.0f} {'':>11s}  "
              f"(subscriber got {got}/{n_blocks}; wall includes process start and discovery)")
        print(f"{'replay publishing loop':28s} {loop_wall:8.3f} {n_blocks / loop_wall:10.0f} "
              f"{samples / loop_wall / 1e6:11.1f} {dur_s / loop_wall:11.0f} {'':>11s}  "
              "(the node's own timing of its publish loop)")
        print("targets: replay >= 100x real time; our reading >= 0.8x rosbags")


if __name__ == "__main__":
    main()
