"""Online modal identification throughput: 15 channels at 2 kHz, 0.1 s blocks, 120 s window,
an update every 2 s of stream (the modal_id node's core, decimation included).

Prints stream seconds processed per wall second (target >= 10: keeps up with a replay at 10x
real time) and the update cadence, next to a batch SSI-cov re-run on each 120 s window (the
naive way of tracking) measured in the same run.

    .venv/bin/python bench/bench_modal_online.py [--seconds 300]
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from maglev_ros.modal.ssi_cov import SSICov  # noqa: E402
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
    print(f"stream: {a.seconds:.0f} s of 15 channels at {FS:g} Hz; window {cfg.window_s:g} s, "
          f"update every {cfg.update_s:g} s -> {n_up} updates")
    print(f"online (ours)      : {wall:7.2f} s wall, {cpu:7.2f} s CPU -> "
          f"{a.seconds / wall:6.1f}x real time by wall clock (target >= 10), "
          f"{a.seconds / cpu:6.1f}x by CPU time")
    # peer: batch SSI-cov on every window (decimated the same way), timed on 3 windows
    ssi = SSICov(block_rows=cfg.block_rows, orders=range(cfg.order_step, cfg.max_order + 1, cfg.order_step),
                 decimate_to_hz=cfg.decimate_to_hz, freq_range_hz=(cfg.fmin_hz, cfg.fmax_hz),
                 n_blocks=cfg.n_blocks, spectrum=False)
    win = int(cfg.window_s * FS)
    t = time.perf_counter()
    for k in range(3):
        ssi.fit(y[k * 4000:k * 4000 + win], FS, model.channels)
    per = (time.perf_counter() - t) / 3
    rt_batch = cfg.update_s / per
    print(f"batch per window   : {per:7.2f} s per update -> {rt_batch:6.1f}x real time "
          f"(online is {a.seconds / wall / rt_batch:.1f}x faster)")


if __name__ == "__main__":
    main()
