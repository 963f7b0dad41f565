"""The suite's node graphs as data (no rclpy): used by ``maglev-ros launch`` and launch/*.launch.py.

Each later capability adds its node here once; both launchers pick it up.
"""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class NodeSpec:
    name: str                       # node name and console script
    module: str                     # python module with main()
    params: dict = field(default_factory=dict)
    needs_bag: bool = False         # only started when a bag is given
    # a processing node ends only when stopped: its end while the graph runs (even with exit
    # code 0, e.g. an outside SIGTERM) is a failure of the graph
    runs_until_stopped: bool = False
    # ends by itself once the replay has finished (the demo's summary): the launcher waits for it
    # before stopping the others
    finishes: bool = False


GRAPHS: dict[str, list[NodeSpec]] = {
    "monitor": [
        NodeSpec("replay", "maglev_ros.nodes.replay", needs_bag=True),
        NodeSpec("irregularity", "maglev_ros.nodes.irregularity", runs_until_stopped=True),
        NodeSpec("modal_id", "maglev_ros.nodes.modal_id", runs_until_stopped=True),
        # history_path: set by the launcher in its output directory (unset: memory only)
        NodeSpec("updater", "maglev_ros.nodes.updater", runs_until_stopped=True),
        NodeSpec("discrepancy", "maglev_ros.nodes.discrepancy", runs_until_stopped=True),
        # the twin measures the irregularity under the vehicle itself (irregularity_source
        # "vehicle"; see maglev_ros.twin.online) and judges vehicle channels only where it has
        NodeSpec("twin", "maglev_ros.nodes.twin", params={"irregularity_source": "vehicle", "dt_max_s": 5e-4},
                 runs_until_stopped=True),
    ],
}


def graph(name: str) -> list[NodeSpec]:
    from maglev_ros.errors import UserError
    if name not in GRAPHS:
        raise UserError(f"unknown graph '{name}' (known: {', '.join(sorted(GRAPHS))})")
    return GRAPHS[name]


def ros_param_args(params: dict) -> list[str]:
    """``-p name:=value`` arguments for a parameter dict (bools lower-case, lists in YAML)."""
    out: list[str] = []
    for k, v in params.items():
        if isinstance(v, bool):
            val = str(v).lower()
        elif isinstance(v, (list, tuple)):
            val = "[" + ",".join(repr(x) if isinstance(x, str) else str(x) for x in v) + "]"
        else:
            val = str(v)
        out += ["-p", f"{k}:={val}"]
    return out
