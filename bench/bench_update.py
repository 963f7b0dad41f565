"""Benchmark: the full two-layer update (ambient modes -> guideway layer -> magnet layer) on simulated
recordings, wall time, CPU time and model evaluations, with the surrogate vs the direct model.

    .venv/bin/python bench/bench_update.py [--quick] [--direct-iterations N] [--with-b]

Runs (same bags, same run):
  A. default: guideway layer on the direct FE model (cheap eigenproblem), magnet layer with the
     Elman surrogate (optimal LHS samples) + MOPSO + GRP + direct polish;
  B. (--with-b) guideway layer with the Elman surrogate instead (shows it is not needed there);
  C. magnet layer with the surrogate replaced by the direct coupled model inside MOPSO. Its full
     budget (particles x (iterations + 1) simulations + polish) would take over an hour, so it runs
     ``--direct-iterations`` iterations (capped: ~150 simulations) and the time of the full budget
     is extrapolated from the measured time per coupled simulation (printed as an extrapolation).
Target: A under 5 minutes on 2 cores. The machine may be shared: the 1-minute load average is
printed before and after each run, and CPU time next to wall time. Prints ratios against A.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))


def _load() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller budgets (smoke run)")
    ap.add_argument("--direct-iterations", type=int, default=2)
    ap.add_argument("--with-b", action="store_true", help="also run B (surrogate in the guideway layer)")
    a = ap.parse_args()
    from test_updating_pipeline import _bag
    from maglev_ros.updating.guideway_layer import GuidewayLayer
    from maglev_ros.updating.magnet_layer import MagnetLayer
    from maglev_ros.updating.pipeline import update_from_bags
    tmp = Path(tempfile.mkdtemp(prefix="bench_update_"))
    t = time.perf_counter()
    amb = _bag(tmp, "amb", "ambient", duration_s=60.0, seed=5)
    p1 = _bag(tmp, "p1", "pass", seed=21)
    print(f"simulated bags in {time.perf_counter() - t:.1f} s ({tmp}); {os.cpu_count()} CPUs")
    ns, pol = (12, 6) if a.quick else (60, 8)
    mopso = dict(n_particles=50, n_iterations=100)

    def run(label, gl, ml):
        l0, c0, t0 = _load(), time.process_time(), time.perf_counter()
        up = update_from_bags(amb, [p1], guideway_layer=gl, magnet_layer=ml)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        g, m = up.guideway, up.magnet
        print(f"{label}: wall {wall:7.1f} s, CPU {cpu:7.1f} s (load {l0:.1f} -> {_load():.1f})"
              f" | guideway {g.wall_time_s:6.1f} s, {g.n_model_evaluations} FE evaluations"
              f" | magnet {m.wall_time_s:7.1f} s, {m.n_model_evaluations} coupled simulations"
              f" | irregularity {up.provenance['irregularity_wall_time_s']:.1f} s"
              f" | NRMSE {up.document['magnet_accel_nrmse']['nominal']:.3f} -> {up.document['magnet_accel_nrmse']['updated']:.3f}",
              flush=True)
        return wall, up
    wa, ua = run("A surrogate (magnet) / direct (guideway)", GuidewayLayer(), MagnetLayer(n_samples=ns, polish_max_nfev=pol, **mopso))
    m = ua.magnet
    print("A gains:", {n: f"{v:.5g} +- {s:.2g} ({'identifiable' if ok else 'not identifiable alone'})"
                      for n, v, s, ok in zip(m.names, m.values, m.std, m.identifiable)})
    print("A identifiable combinations:", [(c["expression"], round(c["value"], 6), round(c["std"], 6))
                                           for c in ua.document["identifiable_combinations"]])
    print(f"target: A under 300 s -> {'met' if wa < 300 else 'NOT met'} ({wa:.0f} s wall)", flush=True)
    if a.with_b:
        wb, ub = run("B surrogate in both layers             ", GuidewayLayer(use_surrogate=True),
                     MagnetLayer(n_samples=ns, polish_max_nfev=pol, **mopso))
        print(f"B/A wall ratio {wb / wa:.2f}; guideway surrogate held-out score {ub.guideway.surrogate_score}")
    it = a.direct_iterations
    wc, uc = run(f"C direct magnet MOPSO ({it} iterations)  ", GuidewayLayer(),
                 MagnetLayer(use_surrogate=False, polish_max_nfev=pol, n_particles=50, n_iterations=it))
    per_sim = uc.magnet.wall_time_s / max(uc.magnet.n_model_evaluations, 1)
    n_full = mopso["n_particles"] * (mopso["n_iterations"] + 1) + (uc.magnet.n_model_evaluations
                                                                   - mopso["n_particles"] * (it + 1))
    full = per_sim * n_full + (wc - uc.magnet.wall_time_s)
    print(f"C: measured {uc.magnet.n_model_evaluations} coupled simulations in {uc.magnet.wall_time_s:.0f} s "
          f"({per_sim:.2f} s each); EXTRAPOLATED full direct budget ({mopso['n_particles']} x "
          f"{mopso['n_iterations'] + 1} + polish = {n_full} simulations): ~{full / 60:.0f} min = {full / wa:.0f} x A")
    print(f"A: {ua.magnet.n_model_evaluations} coupled simulations ({ns} LHS samples + polish + uncertainty) vs "
          f"{n_full} for C at full budget ({n_full / max(ua.magnet.n_model_evaluations, 1):.0f}x)")
    print(f"CPU time of this process: {time.process_time():.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
