"""Benchmark: ``maglev-ros diagnose`` and ``maglev-ros update`` on the sample bags, serial vs a local
pool of worker processes (``--workers N``), wall and CPU time, and whether the outputs are the same.

    .venv/bin/python bench/bench_parallel_verbs.py [--workers 2] [--skip-update] [--skip-diagnose]
        [--samples 60] [--blas-threads-peer]

Each verb runs as the user runs it (a subprocess of the CLI). CPU time is the whole process tree's
(the verb, its forkserver and its workers), sampled every 0.5 s with psutil (a worker's last half
second may be missed). ``--blas-threads-peer`` adds a serial diagnose with BLAS at the library's
default thread count (the verb runs at one: the peer runs the CLI with that limit patched out).
The machine may be shared with other jobs: the 1-minute load average is printed before and after each run; compare
CPU times, and wall ratios only within one run of this script.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BAGS = ROOT / "bags"


def _load() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def run_tree(cmd: list[str], env: dict | None = None) -> tuple[float, float, subprocess.CompletedProcess]:
    """(wall s, CPU s of the process tree, completed process)."""
    import psutil
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    root = psutil.Process(p.pid)
    cpu: dict[int, float] = {}

    def sample():
        try:
            procs = [root] + root.children(recursive=True)
        except psutil.NoSuchProcess:
            return
        for q in procs:
            try:
                t = q.cpu_times()
                cpu[q.pid] = max(cpu.get(q.pid, 0.0), t.user + t.system)
            except psutil.NoSuchProcess:
                pass
    while p.poll() is None:
        sample()
        time.sleep(0.5)
    out, err = p.communicate()
    wall = time.perf_counter() - t0
    return wall, sum(cpu.values()), subprocess.CompletedProcess(cmd, p.returncode, out, err)


def _strip_timing(d):
    """A report without its timing fields (wall/CPU seconds differ between runs by nature)."""
    if isinstance(d, dict):
        return {k: _strip_timing(v) for k, v in d.items() if "wall" not in k and "time_s" not in k}
    if isinstance(d, list):
        return [_strip_timing(x) for x in d]
    return d


# the CLI with diagnose's one-BLAS-thread limit replaced by nothing (the peer of --blas-threads-peer)
BLAS_DEFAULT = ("import contextlib, sys; import maglev_ros.parallel as P, maglev_ros.discrepancy.diagnose as D; "
                "P.one_blas_thread = D.one_blas_thread = contextlib.nullcontext; "
                "from maglev_ros.cli import main; sys.exit(main(sys.argv[1:]))")


def _verb(name: str, args: list[str], workers: int | None, env=None, blas_default=False):
    extra = [] if workers is None else ["--workers", str(workers)]
    entry = ["-c", BLAS_DEFAULT] if blas_default else ["-m", "maglev_ros.cli"]
    cmd = [sys.executable, *entry, name, *args, *extra]
    l0 = _load()
    wall, cpu, r = run_tree(cmd, env)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stderr[-3000:]}")
    label = "serial" if workers is None else f"{workers} workers"
    print(f"  {name:8s} {label:10s} wall {wall:7.1f} s  CPU {cpu:7.1f} s  (load {l0:.1f} -> {_load():.1f})",
          flush=True)
    return wall, cpu, r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--samples", type=int, default=60, help="update --samples (default 60, the verb's)")
    ap.add_argument("--skip-update", action="store_true")
    ap.add_argument("--skip-diagnose", action="store_true")
    ap.add_argument("--blas-threads-peer", action="store_true",
                    help="also a serial diagnose with BLAS at the library's default thread count")
    a = ap.parse_args()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    print(f"{os.cpu_count()} CPUs; the machine may be shared with other jobs (load average shown per run)")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if not a.skip_diagnose:
            print("diagnose --ambient bags/paper_ambient --pass bags/paper_pass")
            base = ["--ambient", str(BAGS / "paper_ambient"), "--pass", str(BAGS / "paper_pass"), "--quiet"]
            res = {}
            runs = [("serial", None, False)]
            if a.blas_threads_peer:
                runs.append(("serial, BLAS default threads", None, True))
            runs.append((f"{a.workers} workers", a.workers, False))
            for label, w, blas_default in runs:
                out = tmp / f"diag_{len(res)}"
                if blas_default:
                    print("  (the next serial run: BLAS at the library's default thread count)")
                wall, cpu, _ = _verb("diagnose", [*base, "--out", str(out), "--no-html"], w, env, blas_default)
                res[label] = (wall, cpu, _strip_timing(json.loads((out / "report.json").read_text())))
            ws, cs, rs = res["serial"]
            for label, (w, c, r) in res.items():
                if label != "serial":
                    print(f"  {label}: wall x{ws / w:.2f} faster than serial, CPU {c / cs:.2f} x serial's; "
                          f"report {'identical' if r == rs else 'DIFFERS'} (timing fields aside)")
        if not a.skip_update:
            print(f"update --ambient bags/paper_ambient --pass bags/paper_pass --samples {a.samples}")
            res = {}
            for label, w in (("serial", None), (f"{a.workers} workers", a.workers)):
                out = tmp / f"upd_{len(res)}.json"
                wall, cpu, _ = _verb("update", ["--ambient", str(BAGS / "paper_ambient"), "--pass",
                                                str(BAGS / "paper_pass"), "--samples", str(a.samples), "--quiet",
                                                "--out", str(out)], w, env)
                res[label] = (wall, cpu, _strip_timing(json.loads(out.read_text())))
            (ws, cs, rs), (w, c, r) = res["serial"], res[f"{a.workers} workers"]
            print(f"  {a.workers} workers: wall x{ws / w:.2f} faster than serial, CPU {c / cs:.2f} x serial's; "
                  f"params {'identical' if r == rs else 'DIFFER'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
