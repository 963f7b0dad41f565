"""``maglev-ros batch VERB (--manifest FILE | --glob PATTERN) --out DIR``: a verb over many recordings.

Each recording's job runs the verb's own code on a Dask worker (a ``LocalCluster`` of one process
per core, or ``--scheduler tcp://host:port``) into ``DIR/<name>/``, which appears whole or not
at all; ``DIR/summary.csv`` / ``summary.parquet`` hold a row per recording, ``DIR/index.html``
links the outputs under a trend plot over the recordings' times (``trend.png``). A rerun skips
the recordings done and redoes those that failed (docs/batch.md).
"""
from __future__ import annotations

from pathlib import Path

from maglev_ros.errors import UserError

NAME = "batch"
HELP = "run info, modes, irregularity, update or diagnose over many recordings on Dask (summary, HTML index, trend)"
ORDER = 80


def add_arguments(p) -> None:
    from maglev_ros.batch.jobs import VERBS
    p.add_argument("verb", choices=sorted(VERBS), metavar="VERB", help=f"the verb: {', '.join(VERBS)}")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--manifest", metavar="FILE",
                     help="CSV or YAML listing the recordings (columns bag, name, ambient, args, time)")
    src.add_argument("--glob", metavar="PATTERN",
                     help="recordings matching this pattern (** recursive; quote it); passes paired "
                          "with the latest ambient recorded before them")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (one sub-directory per recording)")
    p.add_argument("--ambient", metavar="BAG", default=None,
                   help="ambient recording for every pass (update, diagnose; a manifest's column wins)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="run on an existing Dask cluster (tcp://host:port; the paths must be the same there)")
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes of the local cluster (default: the cores)")
    p.add_argument("--allowed-failures", type=int, default=None,
                   help="times a task may take its worker down before it is failed (local cluster; "
                        "default Dask's, 3)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")


def run(args) -> int:
    import importlib.util
    missing = [m for m in ("distributed", "pyarrow") if importlib.util.find_spec(m) is None]
    if missing:          # checked here: a colcon install may lack them
        raise UserError(f"batch needs dask.distributed and pyarrow ({', '.join(missing)} not installed); "
                        "install them with pip install 'dask[distributed]' pyarrow")
    from maglev_ros.batch.engine import dask_client, prepare_out, run_jobs
    from maglev_ros.batch.jobs import VERBS
    from maglev_ros.batch.manifest import jobs_from_glob, jobs_from_manifest
    from maglev_ros.batch.summary import write_summary
    from maglev_ros.progress import for_cli

    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers: expected >= 1, got {args.workers}")
    if args.allowed_failures is not None and args.allowed_failures < 0:
        raise UserError(f"--allowed-failures: expected >= 0, got {args.allowed_failures}")
    if args.scheduler and (args.workers is not None or args.allowed_failures is not None):
        raise UserError("--scheduler: the cluster's own workers and settings are used; "
                        "expected no --workers / --allowed-failures with it")
    if args.ambient and VERBS[args.verb].ambient == "no":
        raise UserError(f"--ambient: {args.verb} takes no ambient recording")
    if args.ambient and not Path(args.ambient).exists():
        raise UserError(f"--ambient {args.ambient}: no such recording")
    out = Path(args.out)
    prepare_out(out)                         # before any work: a bad --out is one line
    with for_cli(args.quiet, f"batch {args.verb}") as progress:
        if args.manifest:
            jobs = jobs_from_manifest(args.manifest, args.verb, args.ambient)
        else:
            jobs = jobs_from_glob(args.glob, args.verb, args.ambient, progress)
        with dask_client(args.scheduler, args.workers, args.allowed_failures) as client:
            results, ran = run_jobs(jobs, out, client, progress)
        paths = write_summary(out.resolve(), results, ran, args.verb)
    failed = [r for r in results if r.status != "done"]
    print(f"batch {args.verb}: {len(results) - len(failed)} of {len(results)} recording(s) done "
          f"({len([r for r in results if r.name in ran and r.status == 'done'])} this run), "
          f"{len(failed)} failed; wrote {', '.join(str(p) for p in paths)}")
    if failed:
        raise UserError(f"{len(failed)} of {len(results)} recording(s) failed (first: {failed[0].name}: "
                        f"{failed[0].error}); their errors are in {out / 'summary.csv'}")
    return 0
