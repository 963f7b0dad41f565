"""Repeatability of the live graph: the demo's graph run N times on the same recordings.

Each run is ``maglev-ros demo --no-analysis`` (ambient, pass and held-out pass through the monitor
graph, each recording's results out before the next) in its own ROS domain and output folder.
Prints, per topic the summary node saw, the message counts of every run and whether its content
digest (sha256 of the messages, wall-clock fields left out: ``maglev_ros.nodes.summary``) was the
same in every run, then the share of output topics identical in all runs and each run's wall time.

    .venv/bin/python bench/bench_repeat.py [--runs 10] [--rate 2] [--out out/bench_repeat]
                                            [--bag B --ambient A --held-out H]
"""
import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


def run_once(k: int, args, out: Path) -> tuple[dict, float, int]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain + k % 20), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONPATH=str(HERE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "maglev_ros.cli", "demo", "--no-analysis", "--quiet", "--out", str(out),
           "--rate", str(args.rate), "--results-timeout", str(args.results_timeout)]
    for opt in ("bag", "ambient", "held_out"):
        if getattr(args, opt) is not None:
            cmd += [f"--{opt.replace('_', '-')}", getattr(args, opt)]
    t0 = time.monotonic()
    with open(out.with_suffix(".log"), "w") as log:
        code = subprocess.call(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
    wall = time.monotonic() - t0
    demo = out / "demo.json"
    graph = json.loads(demo.read_text())["graph"] if demo.exists() else {}
    return graph, wall, code


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--rate", type=float, default=2.0)
    ap.add_argument("--results-timeout", type=float, default=900.0)
    ap.add_argument("--out", default="out/bench_repeat")
    ap.add_argument("--bag")
    ap.add_argument("--ambient")
    ap.add_argument("--held-out")
    ap.add_argument("--domain", type=int, default=180, help="ROS domain of the first run (runs use +0..19)")
    args = ap.parse_args()
    from maglev_ros.commands.demo import expected_outputs
    root = Path(args.out)
    root.mkdir(parents=True, exist_ok=True)
    graphs, walls, codes = [], [], []
    for k in range(args.runs):
        graph, wall, code = run_once(k, args, root / f"run{k:02d}")
        graphs.append(graph)
        walls.append(wall)
        codes.append(code)
        print(f"run {k + 1}/{args.runs}: {wall:.0f} s, exit {code}", flush=True)

    topics = sorted({t for g in graphs for t in g.get("topics", {})})
    print(f"\n{'topic':44s} {'identical':>9s}  messages per run")
    identical = {}
    for t in topics:
        stats = [g.get("topics", {}).get(t, {}) for g in graphs]
        digests = {s.get("digest") for s in stats}
        counts = [s.get("messages", 0) for s in stats]
        identical[t] = len(digests) == 1 and None not in digests
        same = "yes" if identical[t] else ("-" if digests == {None} else f"no ({len(digests)})")
        print(f"{t:44s} {same:>9s}  {' '.join(str(c) for c in counts)}")
    # the outputs the demo requires for the recordings' measured topics (those that carried messages)
    measured = {t for t in topics if t.startswith("/testline/") and any(
        g.get("topics", {}).get(t, {}).get("messages") for g in graphs)}
    wanted = expected_outputs([{"topics": dict.fromkeys(measured)}])
    same = sum(identical.get(t, False) for t in wanted)
    print(f"\noutput topics identical in all {args.runs} runs: {same}/{len(wanted)} "
          f"({same / max(len(wanted), 1):.2f}); runs exiting 0: {codes.count(0)}/{args.runs}; "
          f"wall per run {min(walls):.0f}-{max(walls):.0f} s (max/min {max(walls) / max(min(walls), 1e-9):.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
