"""Benchmark: one append to the parameter history at 100 vs 10 000 records (median of ``--appends``
appends, each one write + fsync), and the ratio; an append-only history should give ~1.

    .venv/bin/python bench/bench_history.py [--appends N] [--dir DIR]

The history is prefilled in one go (records as the updater writes them), then a writer opens it
(the one full read, at open) and the appends are timed. fsync time depends on the disk and on
what else runs: the 1-minute load average is printed with the result.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from maglev_ros.updating.history import SCHEMA, ParameterHistory  # noqa: E402

PARAMS = {n: {"value": v, "unit": u, "std": 0.01 * v, "identifiable": True}
          for n, v, u in (("youngs_modulus_pa", 3.9e10, "Pa"), ("density_kg_m3", 2500.0, "kg/m^3"),
                          ("bearing_stiffness_n_per_m", 3.0e10, "N/m"), ("kp_a_per_m", 1800.0, "A/m"))}


def _prefill(path: Path, n: int) -> None:
    rec = {"schema": SCHEMA, "time_unix_s": 1.7e9, "line": "0123456789abcdef", "parameters": PARAMS,
           "data_used": {"kind": "modes", "frequencies_hz": [3.1, 12.4, 27.9]}, "fit": {"layer": "guideway"}}
    path.write_text("".join(json.dumps({**rec, "revision": i}) + "\n" for i in range(1, n + 1)))


def _append_s(directory: Path, n_records: int, n_appends: int) -> tuple[float, float]:
    """Median seconds per append after ``n_records`` records, and the seconds to open the writer."""
    path = directory / f"history_{n_records}.jsonl"
    _prefill(path, n_records)
    with ParameterHistory(path) as h:
        t0 = time.perf_counter()
        h.open_writer()
        open_s = time.perf_counter() - t0
        times = []
        for i in range(n_appends):
            t0 = time.perf_counter()
            h.append(PARAMS, {"kind": "modes", "i": i}, {"layer": "guideway"}, line="0123456789abcdef")
            times.append(time.perf_counter() - t0)
    return statistics.median(times), open_s


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--appends", type=int, default=50)
    ap.add_argument("--dir", help="where the histories are written (default: a temporary directory)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        print(f"load average (1 min) {os.getloadavg()[0]:.2f}; {args.appends} appends each; directory {d}")
        res = {}
        for n in (100, 10_000):
            res[n], open_s = _append_s(Path(d), n, args.appends)
            print(f"{n:>6} records: append {1e3 * res[n]:7.3f} ms (median), writer open {1e3 * open_s:7.1f} ms")
        print(f"ratio append(10k) / append(100): {res[10_000] / res[100]:.2f}")
        print(f"load average (1 min) {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
