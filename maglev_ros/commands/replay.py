"""``maglev-ros replay BAG``: run the replay node on a bag (options map to its parameters)."""
from __future__ import annotations

import os

from maglev_ros.errors import UserError
from maglev_ros.replay_timing import check_rate

NAME = "replay"
HELP = "publish a recorded bag's topics with their recorded timing (and /clock)"
ORDER = 20


def add_arguments(p) -> None:
    p.add_argument("bag", help="rosbag2 bag (MCAP or sqlite3) or ROS 1 bag")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--rate", "-r", type=float, default=1.0,
                       help="bag seconds per wall second, 0.1-100 (default 1)")
    speed.add_argument("--fast", action="store_true", help="as fast as possible")
    p.add_argument("--start", type=float, default=0.0, metavar="S", help="start offset [s]")
    p.add_argument("--duration", type=float, default=0.0, metavar="S",
                   help="replay only this long [s] (0: to the end)")
    p.add_argument("--loop", action="store_true", help="start again at the end")
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
    if not os.path.exists(args.bag):
        raise UserError(f"{args.bag}: no such bag")
    if not args.fast:
        check_rate(args.rate)
    params = {
        "bag": os.path.abspath(args.bag), "rate": float(args.rate), "fast": args.fast,
        "start_offset_s": float(args.start), "duration_s": float(args.duration),
        "loop": args.loop, "clock": not args.no_clock, "paused": args.paused,
        "progress": not args.quiet, "wait_subscribers": int(args.wait_subscribers),
    }
    out = ["--ros-args"]
    for k, v in params.items():
        val = str(v).lower() if isinstance(v, bool) else (repr(v) if isinstance(v, float) else str(v))
        out += ["-p", f"{k}:={val}"]
    if args.topics:
        out += ["-p", "topics:=[" + ",".join(f"'{t}'" for t in args.topics) + "]"]
    extra = [a for a in args.ros_args if a != "--ros-args"]
    return out + extra


def run(args) -> int:
    from maglev_ros.nodes import require_ros
    require_ros()
    from maglev_ros.nodes import replay as replay_node
    return replay_node.main(["replay"] + ros_arguments(args))
