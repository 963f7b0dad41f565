"""``maglev-ros simulate SCENARIO --out BAG [--seed N] [--set key=value ...]``.

Simulates a test-line record from a scenario (a YAML file or a built-in name: ``paper``,
``paper-ambient``) and writes it as a contract bag, with the hidden truth beside it in
``BAG.truth.json`` (and the true irregularity in ``BAG.irregularity.csv`` for a pass). See
maglev_ros/twin/simulate.py for the scenario keys.
"""
from __future__ import annotations

import json

from maglev_ros.errors import UserError

NAME = "simulate"
HELP = "simulate a test-line recording (vehicle pass or ambient) from a scenario into a contract bag"
ORDER = 40


def add_arguments(p) -> None:
    from maglev_ros.twin.simulate import builtin_scenarios
    names = ", ".join(builtin_scenarios())
    p.add_argument("scenario", metavar="SCENARIO", help=f"scenario YAML file or built-in name ({names})")
    p.add_argument("--out", required=True, help="output bag (rosbag2 directory)")
    p.add_argument("--seed", type=int, default=None, help="random seed (overrides the scenario's)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scenario key, dotted path, YAML value (repeatable), "
                        "e.g. --set speed_mps=10 --set truth.guideway.youngs_modulus_pa=4.2e10")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="bag storage (default mcap)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr (stage, count, ETA)")


def run(args) -> int:
    from maglev_ros import outputs
    from maglev_ros.progress import for_cli
    from maglev_ros.twin.simulate import simulate, truth_paths
    # the bag and its sidecars can be written: checked before the simulation, not after
    outputs.check_parent(args.out, "--out")
    for sidecar in truth_paths(args.out):
        if sidecar.is_dir():
            raise UserError(f"--out {args.out}: {sidecar} is a directory; expected none or a file")
    with for_cli(args.quiet, "simulate") as progress:
        res = simulate(args.scenario, args.out, sets=args.sets, seed=args.seed, overwrite=args.overwrite,
                       storage=args.storage, progress=progress)
    if args.json:
        print(json.dumps(res.to_dict(), indent=1))
        return 0
    print(f"wrote {res.bag}: {res.kind}, {res.duration_s:.2f} s")
    for t, i in res.topics.items():
        print(f"  {t:34s} {i['blocks']:5d} blocks @ {i['rate_hz']:g} Hz  {', '.join(i['channels'])}")
    s = res.summary
    if "magnet_accel_peak_mps2" in s:
        disp = max(s["guideway_disp_peak_m"].values()) if s.get("guideway_disp_peak_m") else 0.0
        print(f"  truth: magnet peak accel {s['magnet_accel_peak_mps2']:.2f} m/s^2, guideway peak "
              f"displacement {disp * 1e3:.3f} mm")
    f = s.get("instrumented_span_freq_hz") or []
    if f:
        print(f"  truth: instrumented span modes {', '.join(f'{x:.2f}' for x in f)} Hz")
    print(f"  truth sidecar: {res.truth_json}" + (f", irregularity: {res.irregularity_csv}"
                                                  if res.irregularity_csv else ""))
    return 0
