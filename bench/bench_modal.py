#!/usr/bin/env python
"""Benchmark: our SSI-cov vs koma-python (covssi + HDBSCAN PoleClusterer) vs pyOMA2 (SSI cov +
clustering), on the same simulated guideway record (15 channels, 500 Hz, 600 s, 5 % sensor noise,
known modes from tests/modal_data.py), in one run. Prints accuracy (worst frequency error,
damping error, MAC, missing / spurious modes in 5-150 Hz) and wall time with ratios.

Also measures the streaming tracker's throughput (15 channels at 2 kHz, 120 s windows updated
every 2 s, decimation to 500 Hz included) against the 10x-real-time target.

Usage: .venv/bin/python bench/bench_modal.py [--duration-s 600] [--seed 1] [--no-stream]
       [--blas-threads 1]
Peers: .venv/bin/pip install koma-python hdbscan pyoma-2
"""
from __future__ import annotations

import argparse
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from maglev_ros.modal.ssi_cov import Mode, SSICov  # noqa: E402
from maglev_ros.modal.stabilization import real_mode_shape  # noqa: E402
from modal_data import assert_modes_match, guideway_model, simulate_ambient  # noqa: E402

FS = 500.0
BR = 40                       # block rows, same for every method
ORDERS = list(range(2, 81, 2))
FMIN, FMAX = 5.0, 150.0


def _modes_from(freqs, zetas, shapes, channels):
    out = []
    for k, (f, z, phi) in enumerate(zip(freqs, zetas, shapes)):
        r = real_mode_shape(np.asarray(phi))
        out.append(Mode(f"P{k}", float(f), float(z), dict(zip(channels, r)), 1.0, 0.0,
                        float("nan"), float("nan")))
    return out


def run_ours(y, channels):
    res = SSICov(block_rows=BR, orders=ORDERS).fit(y, FS, channels)
    return list(res.modes)


def run_koma(y, channels):
    from koma import clustering, oma
    lambd, phi, orders = oma.covssi(y, FS, BR, ORDERS, showinfo=False)
    lam_s, phi_s, ord_s, _ = oma.find_stable_poles(
        lambd, phi, orders, s=2, stabcrit={"freq": 0.01, "damping": 0.1, "mac": 0.02},
        valid_range={"freq": [2 * np.pi * FMIN, 2 * np.pi * FMAX], "damping": [0, 0.15]},
        indicator="freq")
    pc = clustering.PoleClusterer(lam_s, phi_s, ord_s, min_samples=10, min_cluster_size=10)
    args = pc.postprocess(prob_threshold=0.5)
    xi_c, om_c, phi_c, _, _, _ = clustering.group_clusters(*args)
    freqs, zetas, shapes = [], [], []
    for xi, om, ph in zip(xi_c, om_c, phi_c):
        f = om / (2 * np.pi)
        k = int(np.argmin(np.abs(f - np.median(f))))
        freqs.append(np.median(f))
        zetas.append(np.median(xi))
        shapes.append(ph[:, k])
    return _modes_from(freqs, zetas, shapes, channels)


def run_pyoma2(y, channels):
    import logging
    logging.getLogger("pyoma2").setLevel(logging.WARNING)
    from pyoma2.algorithms import SSI
    from pyoma2.algorithms.data.run_params import Clustering
    from pyoma2.setup import SingleSetup
    setup = SingleSetup(y, fs=FS)
    alg = SSI(name="ssicov", method="cov", br=BR, ordmin=2, ordmax=ORDERS[-1], step=2)
    setup.add_algorithms(alg)
    setup.run_by_name("ssicov")
    alg.add_clustering(Clustering(name="auto", quick="Reynders", freqlim=(FMIN, FMAX)))
    alg.run_all_clustering()
    cr = alg.result.clustering_results["auto"]
    return _modes_from(np.asarray(cr.Fn), np.asarray(cr.Xi), np.asarray(cr.Phi).T, channels)


def stream_throughput(duration_s: float, seed: int) -> tuple[float, float]:
    """Stream seconds processed per wall second (steady state, decimation included)."""
    from maglev_ros.modal.tracking import ModeTracker, StreamingSSI
    model = guideway_model(None)
    fs = 2000.0
    y = simulate_ambient(model, fs, duration_s, noise_frac=0.05, seed=seed)
    ssi = SSICov(block_rows=BR, orders=range(4, 61, 4), decimate_to_hz=500.0, spectrum=False,
                 n_blocks=6, freq_range_hz=(FMIN, FMAX))
    st = StreamingSSI(ssi, fs, model.channels, window_s=120.0, update_s=2.0)
    tr = ModeTracker()
    blk = 200                                   # 0.1 s blocks, as a SensorBlock stream
    t0 = time.perf_counter()
    t_first = None
    n_first = 0
    n_updates = 0
    for k in range(0, y.shape[0], blk):
        for res in st.push(y[k:k + blk]):
            tr.update(res, st.time_s)
            n_updates += 1
            if t_first is None:                 # window full: steady state starts
                t_first, n_first = time.perf_counter(), k + blk
    wall_all = time.perf_counter() - t0
    steady = (y.shape[0] - n_first) / fs / (time.perf_counter() - t_first)
    return y.shape[0] / fs / wall_all, steady


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=600.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-stream", action="store_true")
    ap.add_argument("--stream-duration-s", type=float, default=200.0)
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads for every method (0 = library defaults). Default 1: on a "
                         "shared 2-core machine multi-threaded OpenBLAS spin-waits and makes the "
                         "timings erratic")
    args = ap.parse_args(argv)
    if args.blas_threads > 0:
        from threadpoolctl import threadpool_limits
        threadpool_limits(limits=args.blas_threads, user_api="blas")
        print(f"BLAS threads: {args.blas_threads} for all methods")
    model = guideway_model(None)
    print(f"simulating {args.duration_s:.0f} s, 15 channels, {FS:.0f} Hz, 5 % noise; truth "
          f"{np.round(model.frequency_hz, 2).tolist()} Hz")
    y = simulate_ambient(model, FS, args.duration_s, noise_frac=0.05, seed=args.seed)
    rows = []
    for name, fn in (("ours (SSICov)", run_ours), ("koma-python covssi+HDBSCAN", run_koma),
                     ("pyOMA2 SSI cov+Reynders", run_pyoma2)):
        t0 = time.perf_counter()
        try:
            modes = fn(y, model.channels)
        except Exception as exc:  # a peer that fails must not stop the bench
            print(f"!! {name} FAILED: {type(exc).__name__}: {exc}")
            traceback.print_exc(limit=2)
            rows.append((name, None, None))
            continue
        wall = time.perf_counter() - t0
        chk = assert_modes_match(modes, model, FMAX, FMIN)
        rows.append((name, wall, chk))
        print(f"   {name}: {wall:.2f} s", flush=True)
    print()
    print(f"{'method':30s} {'wall s':>8s} {'x ours':>7s} {'max df %':>9s} {'max dz pp':>10s} "
          f"{'min MAC':>8s} {'missing':>8s} {'spurious':>9s}")
    t_ours = rows[0][1]
    for name, wall, chk in rows:
        if wall is None:
            print(f"{name:30s} {'FAILED':>8s}")
            continue
        ratio = wall / t_ours if t_ours else float("nan")
        print(f"{name:30s} {wall:8.2f} {ratio:7.1f} {100 * chk['freq_rel']:9.3f} "
              f"{100 * chk['damping_abs']:10.3f} {chk['mac_min']:8.4f} {len(chk['missing']):8d} "
              f"{len(chk['spurious']):9d}")
    print("(x ours = peer wall time / our wall time; target >= 5x, accuracy equal or better)")
    if not args.no_stream:
        overall, steady = stream_throughput(args.stream_duration_s, args.seed)
        print(f"\nstreaming: 15 ch @ 2 kHz, 120 s window / 2 s update: {steady:.1f} s of stream per "
              f"wall second in steady state ({overall:.1f} including the window fill); target >= 10")
    return 0


if __name__ == "__main__":
    sys.exit(main())
