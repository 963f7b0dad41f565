"""``maglev-ros echo TOPIC``: print a topic's messages (ros2cli is not on PyPI)."""
from __future__ import annotations

# the option set lives with the node, so the `maglev_echo` node and `maglev-ros echo` stay the same
from maglev_ros.nodes._echo_options import add_arguments  # noqa: F401  (the verb's options)

NAME = "echo"
HELP = "print the messages of a topic (SensorBlocks summarised per channel)"
ORDER = 30


def run(args) -> int:
    from maglev_ros.nodes import require_ros
    require_ros()
    from maglev_ros.nodes import echo as echo_node
    return echo_node.run(args)
