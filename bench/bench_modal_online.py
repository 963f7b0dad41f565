"""Online modal identification throughput: 15 channels at 2 kHz, 0.1 s blocks, the node's default
settings (the window grows from 40 s with the stream, the verb's band plan for it), an update every
2 s of stream (the modal_id node's core, decimation included).

Prints stream seconds processed per wall second (target >= 10: keeps up with a replay at 10x
real time) and the update cadence, next to a batch multi-band SSI-cov re-run on one window of
the same plan (the naive way of tracking) measured in the same run.

    .venv/bin/python bench/bench_modal_online.py [--seconds 300]
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from maglev_ros.modal.tracking import OnlineModalConfig, OnlineModalID  # noqa: E402
from modal_data import guideway_model, simulate_ambient  # noqa: E402

FS = 2000.0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=300.0)
    a = ap.parse_args()
    model = guideway_model(seed=0)
    y = simulate_ambient(model, fs_hz=FS, duration_s=a.seconds, seed=1)
    cfg = OnlineModalConfig()
    online = OnlineModalID(cfg)
    nb = int(0.1 * FS)
    t = time.perf_counter()
    c = time.process_time()
    n_up = 0
    for i in range(0, y.shape[0], nb):
        n_up += len(online.push(i / FS, y[i:i + nb], model.channels, FS))
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    print(f"stream: {a.seconds:.0f} s of 15 channels at {FS:g} Hz; window {cfg.first_window_s:g} s "
          f"growing to {online.window_s:g} s, update every {cfg.update_s:g} s -> {n_up} updates")
    print(f"online (ours)      : {wall:7.2f} s wall, {cpu:7.2f} s CPU -> "
          f"{a.seconds / wall:6.1f}x real time by wall clock (target >= 10), "
          f"{a.seconds / cpu:6.1f}x by CPU time")
    # peer: the verb's batch multi-band SSI-cov of the same plan on a window, timed on 3 windows
    from maglev_ros.modal.bands import identify_bands
    win = min(int(online.window_s * FS), y.shape[0] - 8000)
    t = time.perf_counter()
    for k in range(3):
        identify_bands(y[k * 4000:k * 4000 + win], FS, online.plan, model.channels)
    per = (time.perf_counter() - t) / 3
    rt_batch = cfg.update_s / per
    print(f"batch per window   : {per:7.2f} s per update -> {rt_batch:6.1f}x real time "
          f"(online is {a.seconds / wall / rt_batch:.1f}x faster)")


if __name__ == "__main__":
    main()
