"""Node ``modal_id``: guideway modes identified online from /testline/guideway/accel.

Sliding-window SSI-cov (``maglev_ros.modal.tracking.OnlineModalID``) with modes tracked across
updates (stable ids, "new"/"lost"); publishes maglev_msgs/ModalEstimate on /maglev/modes after
every update (every ``update_s`` of stream time once ``window_s`` has filled).

Parameters (also from YAML: ``--params-file config/modal_id.yaml``; read-only, descriptions and
ranges in ``DESCRIPTIONS``): window_s (120), update_s (2), decimate_to_hz (500; 0 = none),
block_rows (40), max_order (60), order_step (4), fmin_hz (5), fmax_hz (150), n_blocks (6),
freq_tol (0.03), mac_min (0.8), max_misses (3), min_confirm (2), channels (string[]; default:
every vertical guideway accelerometer).
"""
from __future__ import annotations

import sys
from dataclasses import fields

from rclpy.node import Node
from std_msgs.msg import String

from maglev_msgs.msg import ModalEstimate, ModalMode, SensorBlock
from maglev_ros.contract import TOPIC_GUIDEWAY_ACCEL, TOPIC_METADATA, parse_metadata
from maglev_ros.modal.tracking import OnlineModalConfig, OnlineModalID
from maglev_ros.nodes._common import BlockGate, run_node, stamp_to_msg
from maglev_ros.nodes._diagnostics import NodeDiagnostics
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import publisher, subscription

TOPIC_MODES = "/maglev/modes"
# the parameters are OnlineModalConfig's fields (defaults from there): description, range
DESCRIPTIONS = {
    "window_s": ("stream time per identification [s]", (0.1, 3600.0)),
    "update_s": ("stream time between identifications [s]", (0.01, 3600.0)),
    "decimate_to_hz": ("decimate the stream to this rate before SSI [Hz] (0: none)", (0.0, 1e6)),
    "block_rows": ("block rows of the SSI Hankel matrix", (1, 100000)),
    "max_order": ("highest model order of the stabilization diagram", (1, 100000)),
    "order_step": ("step between model orders", (1, 1000)),
    "fmin_hz": ("lowest frequency of a mode [Hz]", (0.0, 1e6)),
    "fmax_hz": ("highest frequency of a mode [Hz]", (0.0, 1e6)),
    "n_blocks": ("blocks of the covariance estimate (its uncertainty)", (1, 100000)),
    "freq_tol": ("relative frequency tolerance when tracking a mode", (0.0, 1.0)),
    "mac_min": ("lowest MAC when tracking a mode", (0.0, 1.0)),
    "max_misses": ("updates a mode may miss before it is lost", (0, 100000)),
    "min_confirm": ("updates a new mode needs before it is published as tracked", (0, 100000)),
}


def _params() -> tuple[Param, ...]:
    out = []
    for f in fields(OnlineModalConfig):
        default = getattr(OnlineModalConfig(), f.name)
        text, rng = DESCRIPTIONS.get(f.name, (f"OnlineModalConfig.{f.name} (maglev_ros.modal.tracking)", None))
        out.append(Param(f.name, 0.0 if default is None else default, text, range=rng))
    out.append(Param("channels", [""], "guideway accelerometer channels to identify from (empty: every "
                                       "vertical one in the metadata)"))
    return tuple(out)


class ModalIdNode(Node):
    def __init__(self) -> None:
        super().__init__("modal_id")
        v = declare(self, _params())
        values = {f.name: v[f.name] for f in fields(OnlineModalConfig)}
        values["decimate_to_hz"] = values["decimate_to_hz"] or None
        self.core = OnlineModalID(OnlineModalConfig(**values))
        self.wanted = [c for c in v["channels"] if c]
        self.pub = publisher(self, ModalEstimate, TOPIC_MODES)
        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        subscription(self, String, TOPIC_METADATA, self._on_metadata)
        subscription(self, SensorBlock, TOPIC_GUIDEWAY_ACCEL, self._on_block)

    def _on_metadata(self, msg) -> None:
        self.gate.new_stream()
        if self.wanted:
            return
        try:
            md = parse_metadata(msg.data, TOPIC_METADATA)
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f"metadata unusable: {exc}")
            return
        self.wanted = [sid for sid, s in md.sensors_on_topic(TOPIC_GUIDEWAY_ACCEL).items()
                       if s.direction in (None, "vertical")]

    def _on_block(self, msg) -> None:
        block = self.gate.block(msg, TOPIC_GUIDEWAY_ACCEL)
        if block is None:
            return
        cols = list(range(len(block.channels)))
        if self.wanted:
            cols = [j for j, c in enumerate(block.channels) if c in self.wanted] or cols
        channels = [block.channels[j] for j in cols]
        try:
            updates = self.core.push(block.stamp_s, block.data[:, cols], channels,
                                     block.sample_rate_hz)
        except Exception as exc:  # noqa: BLE001  (bad block: report, keep running)
            self.get_logger().error(f"{TOPIC_GUIDEWAY_ACCEL} block at {block.stamp_s:.3f} s: {exc}")
            return
        for up in updates:
            self.pub.publish(self._message(up, block.stamp_ns))

    def _message(self, update, stamp_ns: int) -> ModalEstimate:
        out = ModalEstimate()
        stamp_to_msg(stamp_ns, out.header)
        out.header.frame_id = "guideway"
        out.method = "ssi-cov"
        out.window_s = float(self.core.config.window_s)
        new = {e.id for e in update.events if e.kind == "new"}
        for m in update.modes:
            mm = ModalMode()
            mm.id = m.id
            mm.status = "new" if m.id in new else "tracked"
            mm.frequency_hz = float(m.frequency_hz)
            mm.damping_ratio = float(m.damping_ratio)
            mm.std_frequency_hz = float(m.std_frequency_hz)
            mm.std_damping_ratio = float(m.std_damping_ratio)
            mm.mpc = float(m.mpc)
            mm.channels = list(m.mode_shape)
            mm.mode_shape = [float(v) for v in m.mode_shape.values()]
            out.modes.append(mm)
        for e in update.events:
            if e.kind == "lost":
                mm = ModalMode()
                mm.id, mm.status, mm.frequency_hz = e.id, "lost", float(e.frequency_hz)
                mm.damping_ratio = mm.std_frequency_hz = mm.std_damping_ratio = mm.mpc = float("nan")
                out.modes.append(mm)
        return out


def main(args=None) -> int:
    return run_node(ModalIdNode, args)


if __name__ == "__main__":
    sys.exit(main())
