"""``maglev-ros update --ambient BAG --pass BAG [--pass BAG ...] [--heldout-pass BAG] --out params.json [--plot DIR]``.

Hierarchical model updating (paper 000 Sec. 4-5, ``maglev_ros.updating.pipeline.update_from_bags``):
guideway modes from the ambient recording (SSI-cov) -> guideway layer (E, rho, kb; the passes'
/testline/guideway/displacement pins the scale of E and rho when present) -> magnet layer (kp, kv,
ka) from the passes' magnet accelerations with the updated guideway. Writes the public
``maglev-params/1`` JSON; ``--plot DIR`` writes pareto.png, frequencies.png, magnet_accel.png (and
magnet_accel_heldout.png).
``--heldout-pass`` judges both twins on passes never fitted (printed, and in ``--details`` provenance).
"""
from __future__ import annotations

import sys
from pathlib import Path

from maglev_ros import outputs
from maglev_ros.errors import UserError

NAME = "update"
HELP = "update the twin's guideway and magnet parameters from ambient + pass recordings"
ORDER = 70


def add_arguments(p) -> None:
    p.add_argument("--ambient", required=True, metavar="BAG", help="ambient-vibration recording (guideway modes)")
    p.add_argument("--pass", dest="passes", action="append", default=[], metavar="BAG",
                   help="vehicle pass recording (magnet layer; repeatable)")
    p.add_argument("--heldout-pass", dest="heldout", action="append", default=[], metavar="BAG",
                   help="vehicle pass never fitted: the nominal and updated twins' magnet accelerations are judged "
                        "on it (repeatable; its rail is measured by every pass)")
    p.add_argument("--out", required=True, metavar="params.json", help="write the maglev-params/1 JSON here")
    p.add_argument("--plot", metavar="DIR", default=None, help="write Pareto / frequency+MAC / acceleration figures here")
    p.add_argument("--details", metavar="OUT.json", default=None,
                   help="also write the full result (Pareto archives, identifiability, provenance)")
    p.add_argument("--max-modes", type=int, default=4, help="modes used by the guideway layer (default 4)")
    p.add_argument("--samples", type=int, default=60, help="optimal-LHS samples for the magnet-layer surrogate (default 60)")
    p.add_argument("--polish-evals", type=int, default=8,
                   help="max residual evaluations of the magnet-layer Levenberg-Marquardt polish on the direct "
                        "coupled model (each iteration adds 3 for its Jacobian; default 8)")
    p.add_argument("--swarm", type=int, nargs=2, default=None, metavar=("PARTICLES", "ITERATIONS"),
                   help="MOPSO size of both layers (default: guideway 100 x 200, magnet 50 x 100)")
    p.add_argument("--max-window-s", type=float, default=None,
                   help="use at most this many seconds of each pass for the magnet layer (default: all)")
    p.add_argument("--seed", type=int, default=0, help="seed of sampling and swarms (default 0)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress on stderr (stage, count, ETA) and no summary table on stdout")
    from maglev_ros.parallel import add_executor_arguments
    add_executor_arguments(p)


def run(args) -> int:
    from maglev_ros.progress import for_cli
    from maglev_ros.updating.pipeline import update_from_bags, update_layers
    from maglev_ros.health import report_lines

    for b in [args.ambient, *args.passes, *args.heldout]:
        if not Path(b).exists():
            raise UserError(f"{b}: no such bag (expected a rosbag2 directory or .mcap/.db3 file)")
    if args.max_modes < 1:
        raise UserError(f"--max-modes: expected >= 1, got {args.max_modes}")
    if args.samples < 8:
        raise UserError(f"--samples: expected >= 8, got {args.samples}")
    if args.polish_evals < 1:
        raise UserError(f"--polish-evals: expected >= 1, got {args.polish_evals}")
    if args.swarm is not None and min(args.swarm) < 2:
        raise UserError(f"--swarm: expected PARTICLES >= 2 and ITERATIONS >= 2, got {args.swarm[0]} {args.swarm[1]}")
    out = Path(args.out)
    # check the outputs before minutes of computation, not after
    outputs.check_file(out, "--out")
    if args.details:
        outputs.check_file(args.details, "--details")
    if args.plot:
        outputs.check_dir(args.plot, "--plot")
    from maglev_ros.parallel import executor_from_options
    with executor_from_options(args.workers, args.scheduler) as executor, for_cli(args.quiet, "update") as progress:
        # the pipeline's messages go to stderr with the progress: stdout stays the result
        gl, ml = update_layers(args.samples, args.polish_evals, args.swarm, args.seed)
        up = update_from_bags(args.ambient, args.passes, heldout=args.heldout, max_modes=args.max_modes,
                              max_window_s=args.max_window_s, guideway_layer=gl, magnet_layer=ml,
                              progress=progress, executor=executor)
        for h in up.provenance["health"]:
            for line in report_lines(h):
                print(f"maglev-ros update: {line}", file=sys.stderr)
        doc = up.document
        # parameters, plots and details replace the earlier set together, or none of them does
        with outputs.Batch() as batch:
            batch.write_json(out, doc, indent=1, option="--out")
            if args.plot:
                from maglev_ros.updating.plot import save_update_plots
                progress.stage("plots")
                plots = save_update_plots(up, args.plot, batch)
            if args.details:
                det = {"document": doc, "guideway": up.guideway.to_dict(),
                       "magnet": None if up.magnet is None else up.magnet.to_dict(), "provenance": up.provenance}
                batch.write_json(args.details, det, indent=1, default=float, option="--details")
    if not args.quiet:
        fm, fn, fu = (doc["frequencies_hz"][k] for k in ("measured", "nominal", "updated"))
        print(f"{'mode':>4s} {'meas Hz':>9s} {'nominal':>9s} {'updated':>9s}")
        for i, (a, b, c) in enumerate(zip(fm, fn, fu)):
            print(f"{i + 1:>4d} {a:9.3f} {b:9.3f} {c:9.3f}")
        for n, v in doc["parameters"].items():
            std = "" if v["std"] is None else f" +- {v['std']:.3g}"
            print(f"{n:>28s} = {v['value']:.5g} {v['unit']}{std}{'' if v['identifiable'] else '  (not identifiable alone)'}")
        if doc["magnet_accel_nrmse"]:
            e = doc["magnet_accel_nrmse"]
            print(f"magnet acceleration NRMSE: nominal {e['nominal']:.3f} -> updated {e['updated']:.3f}")
        h = up.provenance.get("heldout")
        if h:
            print(f"held-out magnet acceleration NRMSE ({', '.join(h['passes'])}): nominal {h['nominal']:.3f} "
                  f"-> updated {h['updated']:.3f}")
        print(f"wrote {out}")
    if args.plot and not args.quiet:
        for p in plots:
            print(f"wrote {p}")
    return 0
