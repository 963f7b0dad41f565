"""The options of the echo node, shared with ``maglev-ros echo`` (no rclpy: the CLI builds its
parser from them without loading ROS 2)."""
from __future__ import annotations


def add_arguments(p) -> None:
    p.add_argument("topic", help="topic to print, e.g. /testline/guideway/accel")
    p.add_argument("--count", "-n", type=int, default=0, help="stop after N messages")
    p.add_argument("--timeout", type=float, default=0.0, help="stop after S seconds (0: never)")
    p.add_argument("--type-timeout", type=float, default=10.0,
                   help="how long to wait for a publisher to appear [s]")
    p.add_argument("--full", action="store_true", help="print every sample")
