"""``maglev-ros replay BAG``: run the replay node on a bag (options map to its parameters)."""
from __future__ import annotations

import os

from maglev_ros.errors import UserError
from maglev_ros.replay_timing import check_rate

NAME = "replay"
HELP = "publish a recorded bag's topics with their recorded timing (and /clock)"
ORDER = 20


def add_arguments(p) -> None:
    p.add_argument("bag", nargs="+", metavar="BAG",
                   help="rosbag2 bag (MCAP or sqlite3) or ROS 1 bag; several are replayed one after the other")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--rate", "-r", type=float, default=1.0,
                       help="bag seconds per wall second, 0.1-100 (default 1)")
    speed.add_argument("--fast", action="store_true", help="as fast as possible")
    p.add_argument("--start", type=float, default=0.0, metavar="S", help="start offset [s]")
    p.add_argument("--duration", type=float, default=0.0, metavar="S",
                   help="replay only this long [s] (0: to the end)")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument("--results-timeout", type=float, default=900.0, metavar="S",
                   help="after each recording, wait at most this long for the nodes of --wait-nodes "
                        "to publish their results (default 900)")
    p.add_argument("--wait-nodes", nargs="+", default=[], metavar="NODE",
                   help="wait for these nodes: in the graph before the start, warm (ready), and done "
                        "with each recording's results before the next one")
    p.add_argument("--topics", nargs="+", default=[], metavar="TOPIC", help="topics to publish")
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    p.add_argument("--paused", action="store_true",
                   help="start paused (space toggles pause in a terminal)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress line")
    p.add_argument("--wait-subscribers", type=int, default=0, metavar="N",
                   help="wait until each topic has N subscribers before starting")
    p.add_argument("--ros-args", dest="ros_args", nargs="...", default=[],
                   help="further ROS arguments (remappings, -p name:=value)")


def ros_arguments(args) -> list[str]:
    """The ``--ros-args`` list that configures the replay node like these CLI options."""
    for bag in args.bag:
        if not os.path.exists(bag):
            raise UserError(f"{bag}: no such bag")
    if args.results_timeout < 0:
        raise UserError(f"--results-timeout: expected seconds >= 0, got {args.results_timeout}")
    if not args.fast:
        check_rate(args.rate)
    params = {
        "rate": float(args.rate), "fast": args.fast,
        "start_offset_s": float(args.start), "duration_s": float(args.duration),
        "loop": args.loop, "clock": not args.no_clock, "paused": args.paused,
        "progress": not args.quiet, "wait_subscribers": int(args.wait_subscribers),
        "results_timeout_s": float(args.results_timeout),
    }
    out = ["--ros-args"]
    bags = [os.path.abspath(b) for b in args.bag]
    out += ["-p", f"bag:={bags[0]}"] if len(bags) == 1 else ["-p", "bags:=" + _yaml_list(bags)]
    for k, v in params.items():
        val = str(v).lower() if isinstance(v, bool) else (repr(v) if isinstance(v, float) else str(v))
        out += ["-p", f"{k}:={val}"]
    if args.topics:
        out += ["-p", "topics:=" + _yaml_list(args.topics)]
    if args.wait_nodes:
        out += ["-p", "wait_nodes:=" + _yaml_list(args.wait_nodes)]
    extra = [a for a in args.ros_args if a != "--ros-args"]
    return out + extra


def _yaml_list(items) -> str:
    """A YAML flow list of strings for ``-p name:=[...]`` (json quoting is YAML quoting)."""
    import json
    return json.dumps([str(i) for i in items])


def run(args) -> int:
    from maglev_ros.nodes import require_ros
    require_ros()
    from maglev_ros.nodes import replay as replay_node
    return replay_node.main(["replay"] + ros_arguments(args))
