"""Node ``twin``: the digital twin running along a recording (thin adapter over twin/online.py).

Subscribes /testline/metadata (latched), /testline/vehicle/position, /testline/vehicle/accel,
/testline/vehicle/gap, /testline/guideway/accel, /testline/guideway/displacement,
/maglev/irregularity (IrregularityProfile) and /maglev/twin/parameters (TwinParameters, latched).
Publishes, for every measured block it can predict, /maglev/twin/predicted/<group> and
/maglev/twin/residual/<group> (SensorBlock, same stamp/rate/channels/units as the measured
block; group = guideway_accel, guideway_displacement, vehicle_accel, vehicle_gap).

Irregularity (see twin/online.py): ``irregularity_source`` vehicle (default: the twin measures
the profile itself from the vehicle streams, point-magnet band), topic (the /maglev/irregularity
message) or random (PSD sample; vehicle residuals are then never published). The vehicle is
stepped with a bounded lag (``max_lag_s``) so that the measured profile lies under every magnet;
a vehicle residual block is published only when valid (every magnet over the measured profile,
settled); its prediction is always published. When the input stops for ``idle_flush_s`` (end of
a replay), the queued remainder is stepped with the final profile and published.

Parameters (``PARAMS``, with descriptions and ranges; read at construction except
``idle_flush_s``): ``irregularity_source`` (vehicle), ``max_lag_s`` (6.0), ``idle_flush_s`` (2.0,
live), ``irregularity_psd`` (default maglev_001), ``irregularity_band_m`` ([1.0, 20.0]),
``seed`` (0), ``method`` (newmark | separated), ``fs_hz`` (0 = fastest measured rate),
``dt_max_s`` (2.5e-4), ``resync_m`` (0.05).
"""
from __future__ import annotations

import array
import sys
import time

from rclpy.node import Node
from std_msgs.msg import String

from maglev_msgs.msg import IrregularityProfile, SensorBlock, TwinParameters
from maglev_ros.contract import parse_metadata
from maglev_ros.nodes._common import BlockGate, run_node
from maglev_ros.nodes._diagnostics import NodeDiagnostics
from maglev_ros.nodes._params import Param, declare
from maglev_ros.nodes._qos import publisher, subscription
from maglev_ros.twin.coupling import METHODS
from maglev_ros.twin.online import IRREGULARITY_SOURCES

TOPIC_IRREGULARITY = "/maglev/irregularity"
TOPIC_PARAMETERS = "/maglev/twin/parameters"
MAX_EARLY_BLOCKS = 2000

PARAMS = (
    Param("irregularity_psd", "maglev_001", "irregularity PSD of the random profile (irregularity_source "
                                            "random)"),
    Param("irregularity_band_m", [1.0, 20.0], "wavelength band of the random profile [m] (low, high)"),
    Param("seed", 0, "seed of the random profile", range=(0, 2**31 - 1)),
    Param("method", "newmark", "vehicle/guideway coupling", choices=METHODS),
    Param("fs_hz", 0.0, "prediction rate [Hz] (0: the fastest measured rate)", range=(0.0, 1e6)),
    Param("dt_max_s", 2.5e-4, "longest integration step [s]", range=(1e-7, 0.1)),
    Param("resync_m", 0.05, "position error at which the twin's vehicle is put back on the measured "
                            "position [m]", range=(0.0, 1e4)),
    Param("irregularity_source", "vehicle", "rail irregularity under the vehicle: measured from the "
                                            "vehicle streams, the /maglev/irregularity topic, or random",
          choices=IRREGULARITY_SOURCES),
    Param("max_lag_s", 6.0, "how far the twin may lag the stream while the rail ahead is measured [s]",
          range=(0.0, 3600.0)),
    Param("idle_flush_s", 2.0, "no input for this long (wall time) ends the stream: the queued "
                               "remainder is stepped and published [s]", range=(0.0, 1e9),
          apply=lambda node, v: setattr(node, "idle_flush_s", v)),
)


def _to_msg(block) -> SensorBlock:
    m = SensorBlock()
    m.header.stamp.sec = int(block.stamp_ns // 1_000_000_000)
    m.header.stamp.nanosec = int(block.stamp_ns % 1_000_000_000)
    m.header.frame_id = block.frame_id
    m.sample_rate_hz = float(block.sample_rate_hz)
    m.channels = list(block.channels)
    m.units = list(block.units)
    buf = array.array("f")
    buf.frombytes(block.data.astype("float32").tobytes())
    m.data = buf
    return m


class TwinNode(Node):
    def __init__(self) -> None:
        super().__init__("twin")
        from maglev_ros.twin.online import GROUP_TOPICS, PREDICTED_PREFIX, RESIDUAL_PREFIX
        v = declare(self, PARAMS)
        self.opts = {
            "psd": v["irregularity_psd"],
            "band_m": list(v["irregularity_band_m"]),
            "seed": v["seed"],
            "method": v["method"],
            "fs_hz": v["fs_hz"] or None,
            "dt_max_s": v["dt_max_s"],
            "resync_m": v["resync_m"],
            "irregularity_source": v["irregularity_source"],
            "max_lag_s": v["max_lag_s"],
        }
        self.idle_flush_s = v["idle_flush_s"]
        self.last_input = time.monotonic()
        self.said: set = set()
        self.core = None
        self.early: list = []
        self.pending_params = None
        self.pending_profile = None
        self.pubs = {}
        self.diagnostics = NodeDiagnostics(self)
        self.gate = BlockGate(self, self.diagnostics)
        for g in GROUP_TOPICS:
            self.pubs[PREDICTED_PREFIX + g] = publisher(self, SensorBlock, PREDICTED_PREFIX + g)
            self.pubs[RESIDUAL_PREFIX + g] = publisher(self, SensorBlock, RESIDUAL_PREFIX + g)
        subscription(self, String, "/testline/metadata", self._on_metadata)
        for topic in ("/testline/vehicle/position", *GROUP_TOPICS.values()):
            subscription(self, SensorBlock, topic, self._cb(topic))
        # latched, as published: the twin gets the newest profile whenever it joins
        subscription(self, IrregularityProfile, TOPIC_IRREGULARITY, self._on_profile)
        subscription(self, TwinParameters, TOPIC_PARAMETERS, self._on_params)
        self.n_in = 0
        self.n_out = 0
        self.create_timer(0.5, self._idle)

    def _once(self, key: str, text: str) -> None:
        if key not in self.said:
            self.said.add(key)
            self.get_logger().info(text)

    def _idle(self) -> None:
        """End of the stream (no input for idle_flush_s): step what is queued, publish it."""
        if self.core is None or not self.core.queued_position_blocks:
            return
        if time.monotonic() - self.last_input < self.idle_flush_s:
            return
        from maglev_ros.errors import UserError
        try:
            outs = self.core.finish()
        except UserError as exc:
            self.get_logger().error(f"twin: {exc}")
            return
        self._publish(outs)

    # ------------------------------------------------------------------ inputs
    def _on_metadata(self, msg) -> None:
        from maglev_ros.errors import UserError
        from maglev_ros.twin.online import OnlineTwin
        self.gate.new_stream()
        try:
            md = parse_metadata(msg.data, "/testline/metadata").raw
            self.core = OnlineTwin(md, psd=self.opts["psd"], band_m=self.opts["band_m"], seed=self.opts["seed"],
                                   method=self.opts["method"], fs_hz=self.opts["fs_hz"],
                                   dt_max_s=self.opts["dt_max_s"], resync_m=self.opts["resync_m"],
                                   irregularity_source=self.opts["irregularity_source"],
                                   max_lag_s=self.opts["max_lag_s"])
        except (UserError, ValueError) as exc:
            self.get_logger().error(f"/testline/metadata: cannot build the twin: {exc}")
            self.core = None
            return
        self.get_logger().info(f"twin built: {len(self.core.guideway_x)} guideway and "
                               f"{len(self.core.magnet_of)} magnet channels predictable")
        if self.pending_params is not None:
            self._on_params(self.pending_params)
        if self.pending_profile is not None:
            self._on_profile(self.pending_profile)
        early, self.early = self.early, []
        for topic, blk in early:
            self._feed(topic, blk)

    def _cb(self, topic: str):
        def on_msg(msg) -> None:
            blk = self.gate.block(msg, topic)
            if blk is None:
                return
            self.n_in += 1
            self.last_input = time.monotonic()
            if self.core is None:
                if len(self.early) < MAX_EARLY_BLOCKS:
                    self.early.append((topic, blk))
                return
            self._feed(topic, blk)
        return on_msg

    def _feed(self, topic: str, blk) -> None:
        from maglev_ros.errors import UserError
        try:
            outs = self.core.on_block(topic, blk)
        except UserError as exc:
            self.get_logger().error(f"{topic}: {exc}")
            return
        self._publish(outs)

    def _publish(self, outs) -> None:
        for o in outs:
            self.pubs[o.predicted_topic].publish(_to_msg(o.predicted))
            if o.valid:
                self.pubs[o.residual_topic].publish(_to_msg(o.residual))
                if o.group.startswith("vehicle"):
                    self._once("valid", f"{o.residual_topic}: publishing residuals from stamp "
                                        f"{o.residual.stamp_ns * 1e-9:.3f} s (measured irregularity under "
                                        f"every magnet, source {self.core.irregularity_source})")
            else:
                self._once("withheld", f"{o.residual_topic}: withheld while the measured irregularity does "
                                       f"not cover every magnet (source {self.core.irregularity_source})")
            self.n_out += 1

    def _on_params(self, msg) -> None:
        from maglev_ros.errors import UserError
        if self.core is None:
            self.pending_params = msg
            return
        try:
            adopted = self.core.set_parameters(list(msg.names), list(msg.values), source_revision=int(msg.revision))
            self.get_logger().info(f"adopted twin parameters rev {msg.revision}: {adopted}")
        except UserError as exc:
            self.get_logger().error(f"{TOPIC_PARAMETERS}: {exc}")

    def _on_profile(self, msg) -> None:
        from maglev_ros.errors import UserError
        if self.core is None:
            self.pending_profile = msg
            return
        try:
            used = self.core.set_irregularity_profile(msg.start_position_m, msg.spacing_m, list(msg.irregularity_m))
            if not used:
                self._once("profile_ignored", f"{TOPIC_IRREGULARITY}: not used; the twin measures its own "
                                              f"point-magnet profile (irregularity_source "
                                              f"{self.core.irregularity_source})")
        except UserError as exc:
            self.get_logger().error(f"{TOPIC_IRREGULARITY}: {exc}")


def main(args=None) -> int:
    return run_node(TwinNode, args)


if __name__ == "__main__":
    sys.exit(main())
