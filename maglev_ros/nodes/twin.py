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
settled); its prediction is always published.

Graph run protocol (:mod:`maglev_ros.nodes._lifecycle`): the node says ``warming`` until every
jitted kernel of the twin is compiled or loaded from numba's cache (:mod:`maglev_ros.twin.warm`, on
a thread at start; the first block would otherwise wait for a compile of up to minutes) and
``ready`` after. At a recording's end (``on_recording_end``) it steps the queued remainder with the
final profile and publishes it before saying ``done``; its status ``detail`` is JSON
``{"recording": k, "residual_blocks": {group: n}}``, the residual blocks it published for that
recording, so that a subscriber (``discrepancy``) knows when it has them all. The blocks are fed
to the twin in (stamp, topic) order whatever order DDS delivers the topics in
(:mod:`maglev_ros.stream_order`), so a replay gives the same predictions on every run and the same
as the offline twin fed the bag in that order. Without a replay
(a live sensor stream: no replay event ever seen) the remainder is stepped when the input stops
for ``idle_flush_s``. A new recording's metadata builds a new twin; blocks that come between a
recording's end and the next metadata wait for it. Parameters (/maglev/twin/parameters) are adopted
at once on a live stream; during a replay's recording, by the next recording's twin (their arrival
time depends on the wall clock, the recording's predictions must not).

Parameters (``PARAMS``, with descriptions and ranges; read at construction except
``idle_flush_s``): ``irregularity_source`` (vehicle), ``max_lag_s`` (6.0), ``idle_flush_s`` (2.0,
live), ``irregularity_psd`` (default maglev_001), ``irregularity_band_m`` ([1.0, 20.0]),
``seed`` (0), ``method`` (newmark | separated), ``fs_hz`` (0 = fastest measured rate),
``dt_max_s`` (2.5e-4), ``resync_m`` (0.05).
"""
from __future__ import annotations

import array
import json
import sys
import threading
import time
from collections import Counter

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
from maglev_ros.nodes._lifecycle import WARMING, NodeLifecycle

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
        self.order = None
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
        self.spent = False                   # the recording ended: its twin takes no more blocks
        self.residual_blocks: Counter = Counter()     # group -> residual blocks of this recording
        self.lifecycle = NodeLifecycle(self, ready=False, diagnostics=self.diagnostics)
        self._set_detail(-1)
        self._warm = None
        threading.Thread(target=self._warm_kernels, daemon=True).start()
        self.create_timer(0.1, self._check_warm)
        self.create_timer(0.5, self._idle)

    # ------------------------------------------------------------------ protocol
    def _warm_kernels(self) -> None:
        from maglev_ros.twin.warm import warm
        try:
            self._warm = warm().summary()
        except Exception as exc:  # noqa: BLE001  (a broken accelerator: the kernel compiles on first use)
            self._warm = f"warm-up failed ({exc}); kernels compile on first use"

    def _check_warm(self) -> None:
        if self._warm is not None and self.lifecycle.status.state == WARMING:
            self.get_logger().info(self._warm)
            self.lifecycle.set_ready(self.lifecycle.status.detail)

    def _set_detail(self, index: int) -> None:
        self.lifecycle.status.detail = json.dumps({"recording": index,
                                                   "residual_blocks": dict(sorted(self.residual_blocks.items()))})

    def on_recording_end(self, index: int) -> None:
        """Step and publish what is queued: the recording's results are out when this returns."""
        if self.core is not None and not self.spent:
            self._finish()
        self.spent = True
        self.get_logger().info(f"recording {index} ended ({self.n_in} blocks taken in all); residual blocks out "
                               f"{dict(sorted(self.residual_blocks.items()))}")
        self._set_detail(index)
        self.residual_blocks.clear()
        self.gate.new_stream()      # the next recording sets its own layout

    def busy(self) -> bool:
        return False             # on_recording_end publishes before it returns

    def _finish(self) -> None:
        from maglev_ros.errors import UserError
        for t, b in self.order.flush():
            self._feed(t, b)
        try:
            outs = self.core.finish()
        except UserError as exc:
            self.get_logger().error(f"twin: {exc}")
            return
        self._publish(outs)

    def _once(self, key: str, text: str) -> None:
        if key not in self.said:
            self.said.add(key)
            self.get_logger().info(text)

    def _idle(self) -> None:
        """Blocks a silent topic no longer holds back; a live stream without a replay stopped (no
        input for idle_flush_s): step what is queued."""
        if self.core is None or self.spent:
            return
        for t, b in self.order.poll(time.monotonic()):
            self._feed(t, b)
        if self.order.released_early:
            self._once("order", f"a topic stayed silent for {self.order.max_silence_s:g} s: blocks of the "
                                f"others were taken without it (this run's predictions depend on arrival order)")
        if self.lifecycle.events_seen:
            return
        if not (self.core.queued_position_blocks or len(self.order)):
            return
        if time.monotonic() - self.last_input < self.idle_flush_s:
            return
        self._finish()

    # ------------------------------------------------------------------ inputs
    def _on_metadata(self, msg) -> None:
        from maglev_ros.errors import UserError
        from maglev_ros.twin.online import OnlineTwin
        try:
            md = parse_metadata(msg.data, "/testline/metadata").raw
            if self.core is not None and not self.spent and md == self.core.metadata.raw:
                return            # the same recording's metadata again (a late joiner's latched copy)
            self.gate.new_stream()
            self.core = OnlineTwin(md, psd=self.opts["psd"], band_m=self.opts["band_m"], seed=self.opts["seed"],
                                   method=self.opts["method"], fs_hz=self.opts["fs_hz"],
                                   dt_max_s=self.opts["dt_max_s"], resync_m=self.opts["resync_m"],
                                   irregularity_source=self.opts["irregularity_source"],
                                   max_lag_s=self.opts["max_lag_s"])
        except (UserError, ValueError) as exc:
            self.get_logger().error(f"/testline/metadata: cannot build the twin: {exc}")
            self.core = None
            return
        self.spent = False
        self.order = self._stream_order(self.core)
        self.get_logger().info(f"twin built: {len(self.core.guideway_x)} guideway and "
                               f"{len(self.core.magnet_of)} magnet channels predictable")
        if self.pending_params is not None:     # the newest parameters carry over to a new recording's twin
            self._adopt(self.pending_params)
        if self.pending_profile is not None:
            self._on_profile(self.pending_profile)
        early, self.early = self.early, []
        for topic, blk in early:
            self._take(topic, blk)

    def _cb(self, topic: str):
        def on_msg(msg) -> None:
            blk = self.gate.block(msg, topic)
            if blk is None:
                return
            self.n_in += 1
            self.last_input = time.monotonic()
            if self.core is None or self.spent:      # wait for this recording's metadata
                if len(self.early) < MAX_EARLY_BLOCKS:
                    self.early.append((topic, blk))
                return
            self._take(topic, blk)
        return on_msg

    @staticmethod
    def _stream_order(core):
        """Blocks fed in (stamp, topic) order whatever their arrival (maglev_ros.stream_order): the
        twin's result depends on what it has seen of every topic."""
        from maglev_ros.contract import TOPIC_VEHICLE_POSITION
        from maglev_ros.stream_order import StreamOrder
        from maglev_ros.twin.online import GROUP_TOPICS
        md = core.metadata
        topics = [TOPIC_VEHICLE_POSITION] if md.run_kind == "pass" else []
        topics += [t for t in GROUP_TOPICS.values() if md.sensors_on_topic(t)]
        return StreamOrder(topics)

    def _take(self, topic: str, blk) -> None:
        for t, b in self.order.add(topic, blk, time.monotonic()):
            self._feed(t, b)

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
                self.residual_blocks[o.group] += 1
                if o.group.startswith("vehicle"):
                    self._once("valid", f"{o.residual_topic}: publishing residuals from stamp "
                                        f"{o.residual.stamp_ns * 1e-9:.3f} s (measured irregularity under "
                                        f"every magnet, source {self.core.irregularity_source})")
            else:
                self._once("withheld", f"{o.residual_topic}: withheld while the measured irregularity does "
                                       f"not cover every magnet (source {self.core.irregularity_source})")
            self.n_out += 1

    def _on_params(self, msg) -> None:
        self.pending_params = msg
        if self.core is None:
            return
        if self.lifecycle.events_seen and not self.spent:
            # a replay: when a revision arrives within a recording depends on the wall clock, so
            # adopting it at once would change the predictions at another block on every run; the
            # next recording's twin adopts it (between recordings the replay waits for the updater)
            self.get_logger().info(f"twin parameters rev {msg.revision} arrived during a recording: the next "
                                   f"recording's twin adopts them (a replay gives the same predictions every run)")
            return
        self._adopt(msg)

    def _adopt(self, msg) -> None:
        from maglev_ros.errors import UserError
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
