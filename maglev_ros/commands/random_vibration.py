"""``maglev-ros random-vibration SCENARIO --out DIR [--quick] [--coupling separated|monolithic]``.

Random vibration of the 3D train-girder system of a scenario (a YAML file or the built-in
``paper001``; maglev_ros/system3d/scenario.py): the deterministic run (static magnet forces
moving over the girder: the mean), then the pseudo-excitation method over the four
irregularity processes (maglev_ros/system3d/pem.py). Writes into DIR:

* ``random_vibration.json`` (schema ``maglev-random-vibration/1``): the scenario, each car's
  time on the girder, the solver's iteration counts, per output the peaks (|mean|, SD, RMS,
  3-sigma bound, PSD peak) and the time series (mean, SD, RMS) and PSD map on the PSD time grid;
* ``rms_envelopes.png``: mean, 3-sigma bounds and RMS of every output along the run;
* ``psd_maps.png``: the time-dependent PSD of every output (time x spatial frequency).

``--quick`` applies the scenario's ``quick`` overrides (coarser step and frequency grid, fewer
girder modes) for a fast check of the same case.
"""
from __future__ import annotations

import time

import numpy as np


NAME = "random-vibration"
HELP = "random vibration of the 3D train-girder system (PEM: mean, SD, RMS, 3-sigma, PSD maps)"
ORDER = 45
SCHEMA = "maglev-random-vibration/1"


def add_arguments(p) -> None:
    p.add_argument("scenario", metavar="SCENARIO", help="scenario YAML file or built-in name (paper001)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--quick", action="store_true",
                   help="apply the scenario's quick overrides (coarser time step, frequency grid, fewer modes)")
    p.add_argument("--coupling", choices=("separated", "monolithic"), default=None,
                   help="vehicle-girder coupling (default: the scenario's)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")


def _series(res, every: int) -> dict:
    lo, hi = res.bounds()
    out = {}
    for i, n in enumerate(res.names):
        out[n] = {"mean": res.mean[i, ::every].tolist(), "sd": res.sd[i, ::every].tolist(),
                  "rms": res.rms[i, ::every].tolist(), "lower_3sigma": lo[i, ::every].tolist(),
                  "upper_3sigma": hi[i, ::every].tolist(), "psd": res.psd[i].tolist()}
    return out


def document(built, res, timings: dict) -> dict:
    sc = built.scenario
    every = max(int(round(sc.psd_time_step_s / sc.time_step_s)), 1)
    return {
        "schema": SCHEMA,
        "scenario": sc.to_dict(),
        "girder": built.solver.dynamics.to_dict(),
        "vehicle_basis_condition": built.solver.basis.condition,
        "cars_on_girder": built.on_girder_s(),
        "frequency_grid": {**built.grid.to_dict(), "centre_rad_per_m": built.grid.centre_rad_per_m.tolist(),
                           "centre_hz": (built.grid.centre_rad_per_m * sc.speed_mps / (2 * np.pi)).tolist()},
        "runs": res.info,
        "timings_s": timings,
        "units": {"psd": "unit^2/(rad/m), one-sided in the spatial angular frequency", "time": "s"},
        "summary": res.summary(),
        "series_time_s": res.time_s[::every].tolist(),
        "psd_time_s": res.psd_time_s.tolist(),
        "series": _series(res, every),
    }


def figures(built, res):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n = len(res.names)
    on = built.on_girder_s()
    lo, hi = res.bounds()
    f1, ax1 = plt.subplots(n, 1, figsize=(9, 2.2 * n), sharex=True, squeeze=False)
    for i, name in enumerate(res.names):
        a = ax1[i, 0]
        a.fill_between(res.time_s, lo[i], hi[i], color="tab:blue", alpha=0.2, label="mean +/- 3 SD")
        a.plot(res.time_s, res.mean[i], "k", lw=0.8, label="mean")
        a.plot(res.time_s, res.rms[i], "tab:red", lw=0.8, label="RMS")
        for c in on:
            a.axvspan(c["enter_s"], c["leave_s"], color="0.5", alpha=0.05)
        a.set_ylabel(f"{name}\n[{res.units[i]}]", fontsize=7)
    ax1[0, 0].legend(fontsize=7, loc="upper right")
    ax1[-1, 0].set_xlabel("time [s] (shaded: cars on the girder)")
    f1.tight_layout()
    f2, ax2 = plt.subplots(n, 1, figsize=(9, 2.4 * n), sharex=True, squeeze=False)
    om = built.grid.centre_rad_per_m
    for i, name in enumerate(res.names):
        a = ax2[i, 0]
        z = res.psd[i].T
        top = max(float(z.max()), 1e-300)
        m = a.pcolormesh(res.psd_time_s, om, np.log10(np.maximum(z, top * 1e-6)), shading="auto", cmap="viridis")
        a.set_yscale("log")
        a.set_ylabel(f"{name}\nOmega [rad/m]", fontsize=7)
        f2.colorbar(m, ax=a, label=f"log10 PSD [{res.units[i]}^2/(rad/m)]")
    ax2[-1, 0].set_xlabel("time [s]")
    f2.tight_layout()
    return f1, f2


def run(args) -> int:
    from maglev_ros import outputs
    from maglev_ros.progress import for_cli
    from maglev_ros.system3d.scenario import build, load_scenario
    out = outputs.check_dir(args.out, "--out")
    sc = load_scenario(args.scenario)
    if args.quick:
        sc = sc.quick_variant()
    if args.coupling:
        from dataclasses import replace
        sc = replace(sc, coupling=args.coupling)
    timings = {}
    t0 = time.perf_counter()
    with for_cli(args.quiet, "random-vibration") as progress:
        progress.stage("assembling vehicle, girder, solver")
        built = build(sc)
        pem = built.pem()
        pem.prepare()
        timings["setup"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        progress.note("mean: static magnet forces over the girder")
        mean, info = pem.mean(sc.n_steps, progress)
        timings["mean_run"] = time.perf_counter() - t1
        t2 = time.perf_counter()
        progress.note(f"PEM: {built.grid.n} frequencies x {len(sc.processes)} processes")
        res = pem.run(sc.n_steps, progress, mean=mean)
        res.info["mean_run"] = info
        timings["pem_run"] = time.perf_counter() - t2
    doc = document(built, res, timings)
    f1, f2 = figures(built, res)
    with outputs.Batch() as batch:
        batch.make_dir(out, "--out")
        batch.write_json(out / "random_vibration.json", doc, indent=None, option="--out")
        batch.write_figure(out / "rms_envelopes.png", f1, "--out", dpi=100)
        batch.write_figure(out / "psd_maps.png", f2, "--out", dpi=100)
    print(f"wrote {out}/random_vibration.json, rms_envelopes.png, psd_maps.png "
          f"({sc.name}{' quick' if args.quick else ''}, {sc.n_steps} steps of {sc.time_step_s} s, "
          f"{built.grid.n} frequencies, {built.solver.dynamics.n} girder coordinates, "
          f"{sum(timings.values()):.1f} s)")
    for c in built.on_girder_s():
        print(f"  car {c['car']}: on the girder {c['enter_s']:.2f} - {c['leave_s']:.2f} s")
    for name, s in doc["summary"].items():
        print(f"  {name:24s} max|mean| {s['max_abs_mean']:.4g}  max SD {s['max_sd']:.4g}  max RMS {s['max_rms']:.4g}"
              f"  max|3 sigma| {s['max_abs_3sigma']:.4g} {s['unit']}  PSD peak {s['psd_peak_hz']:.3g} Hz")
    return 0
