"""Benchmark: real-time factor of the coupled twin (18-DOF vehicle, 5 spans, 1 kHz output).

Prints simulated seconds per wall second (target >= 20) for both coupling schemes, the wall time
per simulated second, and the ratio against a peer measured in the same run: the same kernel run
as plain Python/numpy (what you get without numba).

    .venv/bin/python bench/bench_twin.py
"""
import os
import time

# Small matrices: BLAS threads only contend (2x slower wall time on a loaded 2-core machine).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import maglev_ros.twin.coupling as cp  # noqa: E402
from maglev_ros.twin.design import default_line, twin_config  # noqa: E402


def run(method, duration_s=None, speed=25 / 3.6):
    cfg = twin_config()
    line = default_line(cfg, 5)
    sensors = {f"mid{i + 1}": s.start_m + s.length_m / 2 for i, s in enumerate(line)}
    irr = lambda x: 5e-4 * np.sin(2 * np.pi * x / 5.0)
    t0 = time.perf_counter()
    c0 = time.process_time()
    res = cp.simulate_pass(cfg, line, speed, irr, sensors, duration_s=duration_s, fs_out_hz=1000.0,
                           method=method)
    wall = time.perf_counter() - t0
    run.cpu = time.process_time() - c0
    return res, wall


def main():
    print(f"numba kernel: {cp.HAVE_NUMBA}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    run("newmark", duration_s=0.05)          # warm-up (loads / compiles the kernel)
    run("separated", duration_s=0.05)
    rtf = {}
    for method in ("newmark", "separated"):
        walls, sims, cpus = [], [], []
        for _ in range(3):
            res, wall = run(method)
            walls.append(wall)
            cpus.append(run.cpu)
            sims.append(res.time_s[-1] - res.time_s[0] + 1e-3)
        w = min(walls)
        rtf[method] = sims[0] / w
        print(f"{method:9s}: simulated {sims[0]:.2f} s (5 spans, 25 km/h, {res.n_samples} samples @ 1 kHz) "
              f"in {w:.3f} s wall -> real-time factor {rtf[method]:.1f} (target >= 20); "
              f"{1000 * w / sims[0]:.1f} ms wall per simulated s; max iterations/step {res.iterations.max()}; "
              f"CPU-time real-time factor {sims[0] / min(cpus):.1f} (excludes time other processes took)")
    # peer: the same kernel as plain Python (no numba), short run
    saved = cp._KERNEL, cp._mv
    cp._KERNEL, cp._mv = cp._kernel, (lambda A, x: A @ x)
    try:
        res, wall = run("newmark", duration_s=2.0)
    finally:
        cp._KERNEL, cp._mv = saved
    rtf_py = 2.0 / wall
    print(f"peer (plain-Python kernel, newmark, 2 s): real-time factor {rtf_py:.1f}; "
          f"compiled/plain ratio {rtf['newmark'] / rtf_py:.1f}x")
    ok = min(rtf.values()) >= 20
    print(f"RESULT: real-time factor newmark {rtf['newmark']:.1f}, separated {rtf['separated']:.1f} "
          f"-> {'meets' if ok else 'BELOW'} target 20")


if __name__ == "__main__":
    main()
