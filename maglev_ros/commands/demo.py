"""``maglev-ros demo``: the main job on the bundled sample bags (or any recordings).

1. checks the recordings against the contract;
2. replays the ambient recording, the pass and the held-out pass, in that order, through the
   monitor node graph (irregularity, modal_id, twin, updater, discrepancy), each recording's
   results out before the next (the run protocol), with a summary node counting and
   fingerprinting what flows and a recorder writing the graph's inputs and outputs to
   ``graph.mcap`` (open it in Foxglove); fails (exit 1) naming every output topic that got nothing;
3. analyses them offline with the public verbs: guideway modes of the ambient recording,
   irregularity of the pass, two-layer model update, and the mismatch diagnosis with its
   HTML report: the same recordings the graph saw.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from maglev_ros import outputs
from maglev_ros.errors import UserError

NAME = "demo"
HELP = "run the main job on the bundled sample bag: check, replay through the graph, summarise"
ORDER = 1
SAMPLE_BAG = Path(__file__).resolve().parents[2] / "bags" / "paper_pass"
SAMPLE_AMBIENT = Path(__file__).resolve().parents[2] / "bags" / "paper_ambient"
SAMPLE_HELD_OUT = Path(__file__).resolve().parents[2] / "bags" / "paper_pass2"


def add_arguments(p) -> None:
    p.add_argument("--bag", default=str(SAMPLE_BAG), help="recording (default: bags/paper_pass)")
    p.add_argument("--rate", type=float, default=2.0, help="replay rate through the graph")
    p.add_argument("--ambient", default=str(SAMPLE_AMBIENT),
                   help="ambient recording of the same line (default: bags/paper_ambient)")
    p.add_argument("--held-out", default=str(SAMPLE_HELD_OUT),
                   help="a second pass for the diagnosis: the faster of the passes trains, the other is "
                        "held out (default: bags/paper_pass2; '' for none)")
    p.add_argument("--out", default="out/demo",
                   help="directory for the demo's outputs (the graph's parameter history there is started "
                        "afresh: repeated demos give the same live results)")
    p.add_argument("--namespace", default="", metavar="NS",
                   help="run the node graph in this ROS namespace (beside another line's graph)")
    p.add_argument("--results-timeout", type=float, default=900.0, metavar="S",
                   help="after each recording, wait at most this long for the graph's results (the live "
                        "diagnosis of a pass takes minutes on a busy machine; default 900 s)")
    p.add_argument("--no-analysis", action="store_true",
                   help="stop after the replay through the graph (skip step 3)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress on stderr (stage, count, ETA), here and in the update and diagnosis steps")


def _check(bag: str) -> dict:
    from maglev_ros.bag_reader import BagReader
    with BagReader(bag) as r:
        issues = r.check()
        topics = {t: i.to_dict() for t, i in r.topics.items()}
        summary = {"bag": bag, "duration_s": r.duration_s, "run_kind": r.metadata.run_kind,
                   "description": r.metadata.raw.get("description", ""), "topics": topics,
                   "issues": [i.to_dict() for i in issues]}
    print(f"recording {bag}: {summary['run_kind']}, {summary['duration_s']:.1f} s"
          + (f" - {summary['description']}" if summary["description"] else ""))
    for t, i in sorted(topics.items()):
        chans = ", ".join(i.get("channels", [])[:6]) + (" ..." if len(i.get("channels", [])) > 6 else "")
        rate = f" @ {i['sample_rate_hz']:g} Hz" if i.get("sample_rate_hz") else ""
        print(f"  {t:36s} {i['count']:6d} msgs{rate}  {chans}")
    errors = [i for i in summary["issues"] if i["severity"] == "error"]
    print(f"  contract: {len(errors)} errors, {len(summary['issues']) - len(errors)} warnings")
    if errors:
        raise UserError(f"{bag}: {errors[0]['message']}")
    return summary


def run(args) -> int:
    from maglev_ros.nodes import require_ros
    from maglev_ros.replay_timing import check_rate

    for what, bag in (("--bag", args.bag), ("--ambient", args.ambient), ("--held-out", args.held_out)):
        if bag and not os.path.exists(bag):
            raise UserError(f"{bag}: no such bag ({what})")
    check_rate(args.rate)
    from maglev_ros.launch_graph import check_namespace
    check_namespace(args.namespace)
    if args.results_timeout <= 0:
        raise UserError(f"--results-timeout: expected seconds > 0, got {args.results_timeout}")
    require_ros()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from maglev_ros.progress import for_cli
    with for_cli(args.quiet, "demo") as progress:
        return _run(args, out, progress)


def _run(args, out: Path, progress) -> int:
    progress.stage("1/3 recordings and contract")
    print("== 1. recordings and contract", flush=True)
    bags = [args.ambient, args.bag] + ([args.held_out] if args.held_out else [])
    recordings = [_check(b) for b in bags]

    progress.stage(f"2/3 replay through the node graph at {args.rate:g}x")
    print(f"== 2. replay of {len(bags)} recordings through the node graph at {args.rate:g}x", flush=True)
    flow = _replay_through_graph(args, bags, out)
    problems = _judge_graph(recordings, flow)
    report = {"recordings": recordings, "graph": flow}
    if not args.no_analysis:
        report["analysis"] = _analyse(args.bag, args.ambient, args.held_out or None, out, progress, args.quiet)
    outputs.write_json(out / "demo.json", report, indent=1)
    print(f"== done: {out / 'demo.json'}")
    if problems:
        raise UserError("; ".join(problems) + f" (counts in {out / 'demo.json'})")
    return 0


def _replay_through_graph(args, bags: list[str], out: Path) -> dict:
    from maglev_ros.launch_graph import NodeSpec, recorder_spec
    from maglev_ros.launcher import launch
    graph_json = out / "graph_summary.json"
    graph_json.unlink(missing_ok=True)
    (out / "graph.mcap").unlink(missing_ok=True)
    # the live results must not depend on an earlier demo's accepted parameters
    history = out / "twin_parameters.jsonl"
    for old in (history, history.with_name(history.stem + ".damaged.jsonl")):
        old.unlink(missing_ok=True)
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    summary = NodeSpec("summary", "maglev_ros.nodes.summary", finishes=True,
                       params={"json_out": str(graph_json.resolve()), "reliable": True,
                               "max_s": float(args.results_timeout) * (len(bags) + 1) + 3600.0})
    # reliable: the demo's file holds every message (the recorder keeps up with any node)
    recorder = recorder_spec(out / "graph.mcap", include_inputs=True, reliable=True, sim_time=True)
    # a node that dies raises GraphFailure (one line naming it) after the graph was stopped
    code = launch("monitor", bags=bags, extra=[summary, recorder], env=env, linger_s=0.5,
                  namespace=args.namespace,
                  results_timeout_s=args.results_timeout,
                  overrides={"replay": {"rate": float(args.rate), "progress": False},
                             "updater": {"history_path": str(history.resolve())}})
    if code != 0:       # 130: Ctrl-C stopped the graph
        raise KeyboardInterrupt
    if not graph_json.exists():
        raise UserError("the summary node saw no messages (is DDS on loopback blocked?)")
    if (out / "graph.mcap").exists():
        print(f"  the graph's inputs and outputs: {out / 'graph.mcap'} (MCAP; Foxglove, rosbags)")
    return json.loads(graph_json.read_text())


def expected_outputs(recordings: list[dict]) -> list[str]:
    """The output topics the graph must publish on for these recordings: the twin's prediction and
    residual of every measured group, the modes, irregularity, parameters, mismatch and diagnosis."""
    from maglev_ros.twin.online import GROUP_TOPICS, PREDICTED_PREFIX, RESIDUAL_PREFIX
    measured = {t for rec in recordings for t in rec["topics"]}
    groups = [g for g, t in GROUP_TOPICS.items() if t in measured]
    return ([PREDICTED_PREFIX + g for g in groups] + [RESIDUAL_PREFIX + g for g in groups]
            + ["/maglev/modes", "/maglev/irregularity", "/maglev/twin/parameters", "/maglev/mismatch",
               "/maglev/diagnosis"])


def _judge_graph(recordings: list[dict], flow: dict) -> list[str]:
    """Print what went through the graph and what it made; the problems found, one phrase each."""
    problems = []
    topics = flow.get("topics", {})
    seen = {r["index"]: r for r in flow.get("recordings", [])}
    short = []
    for k, rec in enumerate(recordings):
        expected = {t: i["count"] for t, i in rec["topics"].items()}
        got = seen.get(k, {}).get("received", {})
        lost = {t: (n, got.get(t, 0)) for t, n in expected.items() if got.get(t, 0) != n}
        print(f"  recording {k} {rec['bag']}: {sum(got.values())} of {sum(expected.values())} messages "
              f"through the graph" + (f"; missing on {', '.join(sorted(lost))}" if lost else ""))
        if lost:
            short.append(f"recording {k} ({', '.join(f'{t} {g} of {n}' for t, (n, g) in sorted(lost.items()))})")
    if not flow.get("finished"):
        problems.append("the replay did not finish (no 'finished' event reached the summary)")
    if short:
        problems.append("messages missing in " + "; ".join(short))
    elif flow.get("finished"):
        print("  every recorded message went through the graph")
    wanted = expected_outputs(recordings)
    print("  graph outputs: " + ", ".join(f"{t} {topics.get(t, {}).get('messages', 0)}" for t in wanted))
    empty = [t for t in wanted if not topics.get(t, {}).get("messages", 0)]
    if empty:
        print(f"  NO messages on {', '.join(empty)}", flush=True)
        problems.append(f"the graph published nothing on {', '.join(empty)}")
    return problems


def _analyse(bag: str, ambient: str, held_out: str | None, out: Path, progress, quiet: bool = False) -> dict:
    """Step 3: the offline verbs on the recordings, outputs under ``out``; the long ones (update,
    diagnose) show their own progress under the demo's."""
    from maglev_ros.cli import main as cli
    if not os.path.exists(ambient):
        raise UserError(f"{ambient}: no such bag (the ambient recording for the modes)")
    if held_out and not os.path.exists(held_out):
        raise UserError(f"{held_out}: no such bag (the held-out pass for the diagnosis)")
    extra = ["--pass", held_out] if held_out else []
    q = ["--quiet"] if quiet else []
    steps = [
        ("guideway modes (ambient)", ["modes", ambient, "--json", str(out / "modes.json"),
                                      "--plot", str(out / "stabilization.png")]),
        ("irregularity (pass)", ["irregularity", bag,
                                 "--out", str(out / "irregularity.csv"),
                                 "--json", str(out / "irregularity.json"),
                                 "--plot", str(out / "irregularity.png")]),
        ("model update (ambient + pass)", ["update", "--ambient", ambient, "--pass", bag,
                                           "--out", str(out / "params.json"),
                                           "--plot", str(out / "update"), *q]),
        ("mismatch diagnosis", ["diagnose", "--ambient", ambient, "--pass", bag, *extra,
                                "--out", str(out / "diagnosis"), *q]),
    ]
    done = {}
    progress.stage("3/3 offline analysis")      # no ETA: the steps take 1 s to minutes
    for k, (title, argv) in enumerate(steps, start=1):
        progress.advance(0, note=f"3.{k} {title}")
        print(f"== 3.{k} {title}: maglev-ros {' '.join(argv)}", flush=True)
        code = cli(argv)
        if code != 0:
            raise UserError(f"step 3.{k} ({title}) failed with code {code}")
        done[title] = argv
        progress.advance(note=f"3.{k} {title}")
    diag = json.loads((out / "diagnosis" / "report.json").read_text())
    print(f"== twin vs recording: NRMSE {diag['fit_before']['nrmse']:.3f} before, "
          f"{diag['fit_after']['nrmse']:.3f} after the accepted physics")
    for m in diag["missing_physics"]:
        print(f"   missing physics: {m['effect']} ({m['category']}): {m['explanation']}")
    if not diag["missing_physics"]:
        print("   missing physics: none accepted")
    print(f"   report: {out / 'diagnosis' / 'report.html'}")
    return {"steps": done, "diagnosis": {k: diag[k] for k in ("fit_before", "fit_after",
                                                              "missing_physics")}}
