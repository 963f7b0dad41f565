"""``maglev-ros echo TOPIC``: print a topic's messages (ros2cli is not on PyPI)."""
from __future__ import annotations

NAME = "echo"
HELP = "print the messages of a topic (SensorBlocks summarised per channel)"
ORDER = 30


def add_arguments(p) -> None:
    # The option set lives with the node so `echo` and `maglev-ros echo` stay the same.
    p.add_argument("topic", help="topic to print, e.g. /testline/guideway/accel")
    p.add_argument("--count", "-n", type=int, default=0, help="stop after N messages")
    p.add_argument("--timeout", type=float, default=0.0, help="stop after S seconds (0: never)")
    p.add_argument("--type-timeout", type=float, default=10.0,
                   help="how long to wait for a publisher to appear [s]")
    p.add_argument("--full", action="store_true", help="print every sample")


def run(args) -> int:
    from maglev_ros.nodes import require_ros
    require_ros()
    from maglev_ros.nodes import echo as echo_node
    return echo_node.run(args)
