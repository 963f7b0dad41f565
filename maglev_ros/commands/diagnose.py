"""``maglev-ros diagnose --ambient BAG --pass BAG [--pass BAG ...] --out DIR``.

Calibrates the twin on the fastest pass, locates where twin and recordings differ, tests the
catalogue of missing physics (held out on the other passes) and writes DIR/report.json
(schema ``maglev-diagnosis/1``) and DIR/report.html (self-contained, plots inline).
"""
from __future__ import annotations

import sys
from pathlib import Path

from maglev_ros import outputs
from maglev_ros.errors import UserError

NAME = "diagnose"
HELP = "locate twin/recording mismatches, name the missing physics, fit it, report (JSON + HTML)"
ORDER = 60


def add_arguments(p) -> None:
    p.add_argument("--ambient", metavar="BAG", help="ambient-vibration recording (run.kind ambient)")
    p.add_argument("--pass", dest="passes", metavar="BAG", action="append", required=True,
                   help="pass recording; the first calibrates, the others are held out (repeatable)")
    p.add_argument("--out", metavar="DIR", required=True, help="output directory (report.json, report.html)")
    p.add_argument("--no-html", action="store_true", help="write report.json only")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr (stage, count, ETA)")
    from maglev_ros.parallel import add_executor_arguments
    add_executor_arguments(p)


def run(args) -> int:
    from maglev_ros.progress import for_cli
    for b in [*args.passes, *([args.ambient] if args.ambient else [])]:
        if not Path(b).exists():     # a one-line error before any progress line
            raise UserError(f"{b}: no such bag (expected a rosbag2 directory or .mcap/.db3 file)")
    from maglev_ros.parallel import executor_from_options
    outputs.check_dir(args.out, "--out")        # before the diagnosis, not after
    with executor_from_options(args.workers, args.scheduler) as executor, for_cli(args.quiet, "diagnose") as progress:
        d, out = _diagnose(args, progress, executor)
    rep = d.to_dict()
    print(f"fit before {rep['fit_before']['nrmse']:.3f}, after {rep['fit_after']['nrmse']:.3f}; "
          f"{len(rep['mismatches'])} mismatch(es); missing physics: "
          f"{', '.join(m['effect'] for m in rep['missing_physics']) or 'none'}")
    floor = (rep.get("calibration") or {}).get("fit_floor")
    if floor:
        print(f"calibrated fit {floor['calibrated_nrmse']:.3f}, of which the gap sensors' noise in the rail "
              f"{floor['rail_uncertainty_nrmse']:.3f} (report: calibration.fit_floor)")
    print(f"wrote {out / 'report.json'}" + ("" if args.no_html else f" and {out / 'report.html'}"))
    return 0


def _diagnose(args, progress, executor):
    from maglev_ros.discrepancy.diagnose import diagnose
    from maglev_ros.discrepancy.recording import load_recording
    progress.stage("load recordings", total=len(args.passes) + bool(args.ambient))
    passes = [load_recording(p) for p in progress.steps(args.passes, str)]
    ambient = None
    if args.ambient:
        ambient = load_recording(args.ambient)
        progress.advance(note=args.ambient)
        if ambient.kind != "ambient":
            raise UserError(f"{args.ambient}: run.kind: expected 'ambient' for --ambient, got {ambient.kind!r}")
    out = Path(args.out)
    # what the sensor-health check did (recordings read from bags carry it)
    health = [h for h in (getattr(r, "health", None) for r in (*passes, ambient)) if h is not None]
    for h in health:
        for line in h.lines():
            print(f"maglev-ros diagnose: {line}", file=sys.stderr)
    d = diagnose(passes, ambient, progress=progress, executor=executor)
    doc = {**d.to_dict(), "health": [h.to_dict() for h in health]}
    # report.json and report.html replace the earlier pair together, or neither does
    with outputs.Batch() as batch:
        batch.make_dir(out, "--out")
        batch.write_json(out / "report.json", doc, indent=1, option="--out")
        if args.no_html:
            batch.remove(out / "report.html")    # an earlier report's HTML would not match the JSON
        else:
            from maglev_ros.discrepancy.report_html import render
            progress.stage("write the HTML report")
            batch.write_text(out / "report.html", render(d), option="--out")
    return d, out
