"""ROS 2 nodes: thin adapters between topics and the science core. Only this package imports rclpy.

The console scripts (``maglev_<node>`` from pip, ``<node>`` in colcon's ``lib/maglev_ros``) enter
through the ``*_main`` functions below, which first check that ROS 2 and the suite's messages are
importable and otherwise say in one line how to get them.

Every SensorBlock a node takes passes ``_common.BlockGate`` (a malformed block is dropped, counted,
logged once per kind); each such node publishes its health on /diagnostics (``_diagnostics``).
Message classes come only from ``_common.ALLOWED_TYPES``.
"""
from __future__ import annotations

import functools
import importlib
import importlib.util
import pkgutil
import sys

from maglev_ros.errors import UserError

HOW_TO_GET_ROS = ("run scripts/install from the maglev_ros source tree (ROS 2 wheels from PyPI and "
                  "maglev_msgs built from msg_defs/), or source a ROS 2 install and build msg_defs/ "
                  "with colcon; the offline verbs (info, modes, irregularity, update, diagnose, "
                  "simulate) need neither")


def require_ros() -> None:
    """Raise UserError naming what is missing when rclpy, maglev_msgs or diagnostic_msgs cannot be
    imported."""
    missing = [m for m in ("rclpy", "maglev_msgs", "diagnostic_msgs") if importlib.util.find_spec(m) is None]
    if missing:
        raise UserError(f"the ROS 2 nodes need {' and '.join(missing)} (not installed): "
                        + HOW_TO_GET_ROS)
    try:
        importlib.import_module("maglev_msgs.msg")
        importlib.import_module("maglev_msgs.srv")     # the replay's services (a build before them lacks it)
        importlib.import_module("rclpy")
    except ImportError as exc:   # e.g. the rmw library of the ROS 2 wheels is missing
        raise UserError(f"ROS 2 is installed but does not load ({exc}): " + HOW_TO_GET_ROS) from None


def _run(name: str) -> int:
    try:
        require_ros()
    except UserError as exc:
        print(f"maglev_{name}: error: {exc}", file=sys.stderr)
        return 1
    return importlib.import_module(f"maglev_ros.nodes.{name}").main()


# the console scripts' entry points: replay_main, echo_main, ... (one per node module)
NODES = tuple(sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")))
for _name in NODES:
    globals()[f"{_name}_main"] = functools.partial(_run, _name)
