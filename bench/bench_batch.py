"""Throughput of ``maglev-ros batch`` (recordings per hour and speed-up) on this machine.

Runs the same manifest (the bundled sample passes, repeated under distinct names, each with the
ambient recording) three ways, each into a fresh output directory:

  1. a LocalCluster of 1 worker process,
  2. a LocalCluster of 2 worker processes,
  3. ``dask scheduler`` + two ``dask worker`` processes started separately (as on two machines),
     through ``--scheduler``;

and prints wall time, recordings per hour and the speed-up over (1) measured in the same run. A
direct run of the verb on one recording (``maglev-ros VERB ...`` in this process) is timed too,
so the batch's per-recording cost can be set against it. The machine may be shared: the load
average before and after each run is printed beside the figures.

    python bench/bench_batch.py --verb diagnose --jobs 4
    python bench/bench_batch.py --verb update --jobs 6 --args "--samples 12 --swarm 12 8"
"""
from __future__ import annotations

import argparse
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

BAGS = ROOT / "bags"
PASSES = [BAGS / "paper_pass", BAGS / "paper_pass2"]
AMBIENT = BAGS / "paper_ambient"


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _manifest(path: Path, n: int, args: str) -> Path:
    lines = ["bag,name,ambient,args"]
    for k in range(n):
        lines.append(f"{PASSES[k % len(PASSES)]},job{k:02d},{AMBIENT},{shlex.quote(args) if args else ''}")
    path.write_text("\n".join(lines) + "\n")
    return path


def _timed(argv: list[str]) -> float:
    from maglev_ros.cli import main
    t0 = time.perf_counter()
    code = main(argv)
    dt = time.perf_counter() - t0
    if code != 0:
        raise SystemExit(f"bench: maglev-ros {' '.join(argv)} exited {code}")
    return dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--verb", choices=("diagnose", "update"), default="diagnose")
    ap.add_argument("--jobs", type=int, default=4, help="recordings in the manifest (default 4)")
    ap.add_argument("--args", default="", help="further arguments for every job (e.g. update's --samples)")
    ap.add_argument("--skip", nargs="*", default=(), choices=("direct", "1", "2", "cli"),
                    help="leave out some of the runs")
    a = ap.parse_args()
    from dask_cluster import dask_cli_cluster
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        tmp = Path(tmp)
        man = _manifest(tmp / "manifest.csv", a.jobs, a.args)
        print(f"bench_batch: {a.verb}, {a.jobs} recording(s) (sample passes with the sample ambient), "
              f"extra arguments {a.args!r}; {os.cpu_count()} cores; load average before: {_load()}")
        rows = []
        if "direct" not in a.skip:
            out = tmp / "direct"
            argv = ([a.verb, "--ambient", str(AMBIENT), "--pass", str(PASSES[0])]
                    + (["--out", str(out)] if a.verb == "diagnose" else ["--out", str(out) + ".json"])
                    + ["--quiet"] + shlex.split(a.args))
            dt = _timed(argv)
            print(f"  direct {a.verb} of one recording in this process: {dt:.1f} s "
                  f"(load {_load()})")
        base = None
        for label, extra in (("1", ["--workers", "1"]), ("2", ["--workers", "2"]), ("cli", None)):
            if label in a.skip:
                continue
            out = tmp / f"out_{label}"
            argv = ["batch", a.verb, "--manifest", str(man), "--out", str(out), "--quiet"]
            if extra is None:
                with dask_cli_cluster(tmp / "cluster", n_workers=2) as address:
                    dt = _timed(argv + ["--scheduler", address])
                name = "dask scheduler + 2 dask worker processes"
            else:
                dt = _timed(argv + extra)
                name = f"LocalCluster, {label} worker(s)"
            per_h = a.jobs / dt * 3600.0
            if label == "1":
                base = dt
            rows.append((name, dt, per_h, None if base is None else base / dt))
            print(f"  {name:42s} {dt:7.1f} s  {per_h:7.1f} recordings/h"
                  + ("" if base is None else f"  speed-up {base / dt:4.2f}") + f"  (load {_load()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
